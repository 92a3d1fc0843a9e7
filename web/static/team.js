// Team page: sign in with the team token (common.js keeps it), register, upload (checked by the validator
// before anything is stored, then followed live until scored), history.
"use strict";

const FINAL = ["scored", "failed", "cancelled"];
const PAGE = JSON.parse($("#page-data").textContent);
const scoreOf = (submission, version) => {
  const results = submission.results?.[version] || {};
  return (results.all || results.public || {}).score;
};

// --- signing in and out -------------------------------------------------------------------------------

function showQuotas(list) {
  const quotas = $("#quotas");
  quotas.replaceChildren();
  for (const quota of list) {
    const item = document.createElement("li");
    const left = quota.limit === null ? "no limit" : `${Math.max(0, quota.limit - quota.used)} of ${quota.limit} left`;
    item.textContent = `${quota.phase}, ${quota.quota.replace("_", " ")}: ${left}` +
      (quota.resets_at ? ` (resets ${when(quota.resets_at)} UTC)` : "");
    quotas.append(item);
  }
  if (!list.length) quotas.append(Object.assign(document.createElement("li"), { textContent: "No open phase." }));
}

// After an upload (accepted or refused), what is left of each quota.
const refreshQuotas = () => api("GET", "/me").then((me) => showQuotas(me.quotas)).catch(() => {});

async function showTeam() {
  const me = await api("GET", "/me");
  if (me.scope !== "team") throw new ApiError(403, { detail: "This is not a team token." });
  $("#team-name").textContent = me.team;
  $("#approval").textContent = me.approval;
  $("#approval").title = me.approval === "approved" ? "" : "an organiser approves teams before their first upload";
  showQuotas(me.quotas);
  $("#signed-out").hidden = true;
  $("#signed-in").hidden = false;
  const [open] = await Promise.all([loadPhases(), loadHistory()]);
  // Said before a form is filled: who may not upload now, and why.
  const refusal = {
    pending: "Your team is waiting for an organiser's approval: you can upload once it is approved. Your token stays valid meanwhile.",
    rejected: "An organiser rejected your team's registration: it cannot upload. Write to the organisers if you think this is a mistake.",
  }[me.approval] || (open ? "" : "No phase is open for submissions now: the quota list above shows when one is.");
  $("#cannot-upload").textContent = refusal;
  $("#cannot-upload").hidden = !refusal;
  $("#upload").hidden = Boolean(refusal);
}

$("#signin").addEventListener("submit", async (event) => {
  event.preventDefault();
  sessionStorage.setItem(TOKEN_KEY, $("#token").value.trim());
  $("#signin-error").textContent = "";
  try {
    await showTeam();
  } catch (error) {
    sessionStorage.removeItem(TOKEN_KEY);
    $("#signin-error").textContent = describeError(error);
  }
});

$("#signout").addEventListener("click", () => {
  sessionStorage.removeItem(TOKEN_KEY);
  window.location.reload();
});

$("#register").addEventListener("submit", async (event) => {
  event.preventDefault();
  const data = new FormData(event.target);
  const members = String(data.get("members") || "").split(",").map((name) => name.trim()).filter(Boolean);
  $("#register-error").textContent = "";
  try {
    const created = await fetch(`${API}/teams`, {
      method: "POST",
      headers: { "Content-Type": "application/json" },
      body: JSON.stringify({ name: data.get("name"), affiliation: data.get("affiliation"), members }),
    });
    const body = await created.json().catch(() => ({}));
    if (!created.ok) throw new ApiError(created.status, body);
    $("#new-token").textContent = body.token;
    $("#registered").hidden = false;
    $("#token").value = body.token;
  } catch (error) {
    $("#register-error").textContent = describeError(error);
  }
});

// --- upload ---------------------------------------------------------------------------------------------

async function loadPhases() {
  const phases = await api("GET", "/phases");
  const select = $("#phase");
  select.replaceChildren();
  const open = phases.filter((p) => p.open);
  for (const phase of open) select.append(new Option(`${phase.name} (split ${phase.split})`, phase.name));
  if (open.length) select.value = open[open.length - 1].name; // the server's default: the open phase that opened last
  return open.length > 0;
}

const SHOWN_PROBLEMS = 25;

function showProblems(problems, all = false) {
  const table = $("#problems");
  const body = table.tBodies[0];
  body.replaceChildren();
  for (const problem of all ? problems : problems.slice(0, SHOWN_PROBLEMS)) {
    const row = body.insertRow();
    cell(row, problem.token ?? "–");
    cell(row, problem.field ?? "–");
    cell(row, problem.message);
  }
  if (!all && problems.length > SHOWN_PROBLEMS) {
    const row = body.insertRow();
    const more = button(`show all ${problems.length} problems`, () => showProblems(problems, true));
    cell(row, more).colSpan = 3;
  }
  table.hidden = problems.length === 0;
}

function say(text, failed = false) {
  $("#upload-status").textContent = text;
  $("#upload-status").className = failed ? "error" : "note";
}

async function follow(id) {
  $("#progress").hidden = false;
  for (;;) {
    const submission = await api("GET", `/submissions/${id}`);
    $("#progress-bar").value = submission.progress;
    $("#progress-text").textContent = `${submission.status}, ${submission.progress}%`;
    if (FINAL.includes(submission.status)) {
      const link = document.createElement("a");
      link.href = `/submissions/${id}`;
      link.textContent = "see its results";
      $("#upload-status").replaceChildren(
        submission.status === "scored"
          ? `Submission ${id} is scored: ${[...PAGE.versions].reverse().filter((v) => v in submission.results).map((v) => `${PAGE.score_labels[v]} ${v} ${pct(scoreOf(submission, v))}`).join(", ")}. `
          : `Submission ${id} ${submission.status}: ${submission.error || "no detail"}. `,
        link,
      );
      await loadHistory();
      return;
    }
    await new Promise((resolve) => setTimeout(resolve, 1000));
  }
}

$("#upload").addEventListener("submit", async (event) => {
  event.preventDefault();
  // The phase goes before the file: the server reads the file as it arrives, within the phase's split.
  const fields = new FormData(event.target);
  const form = new FormData();
  const check = new FormData();
  if (fields.get("phase")) [form, check].forEach((data) => data.append("phase", fields.get("phase")));
  for (const [key, value] of fields.entries()) if (key !== "phase" && value !== "") form.append(key, value);
  check.append("file", fields.get("file"));
  showProblems([]);
  $("#progress").hidden = true;
  $("#upload-button").disabled = true;
  try {
    say("Checking the file…");
    await api("POST", "/submissions:validate", { form: check });
    say("The file is valid. Submitting…");
    const accepted = await api("POST", "/submissions", { form });
    say(`Submission ${accepted.id} is queued.`);
    refreshQuotas();
    await follow(accepted.id);
  } catch (error) {
    if (error instanceof ApiError && Array.isArray(error.body.problems)) {
      say(`${error.message}. Fix them and upload again; nothing was stored.`, true);
      showProblems(error.body.problems);
    } else {
      say(describeError(error), true);
    }
  } finally {
    $("#upload-button").disabled = false;
    refreshQuotas();
  }
});

// --- history --------------------------------------------------------------------------------------------

async function edit(id, changes) {
  $("#history-status").textContent = "";
  try {
    await api("PATCH", `/submissions/${id}`, { json: changes });
  } catch (error) {
    $("#history-status").textContent = describeError(error);
  }
  await loadHistory();
}

function openEditor(submission) {
  const dialog = $("#edit");
  const form = $("#edit-form");
  $("#edit-id").textContent = submission.id;
  for (const name of ["method", "authors", "institution", "country", "tech_report_url", "code_url"]) {
    form.elements[name].value = submission[name] || "";
  }
  $("#edit-error").textContent = "";
  dialog.returnValue = "";
  dialog.showModal();
  dialog.onclose = async () => {
    if (dialog.returnValue !== "save") return;
    const changes = {};
    for (const name of ["method", "authors", "institution", "country", "tech_report_url", "code_url"]) {
      const value = form.elements[name].value.trim();
      if (value !== (submission[name] || "")) changes[name] = value === "" && name.endsWith("_url") ? null : value;
    }
    if (Object.keys(changes).length) await edit(submission.id, changes);
  };
}

// The entry's state as the organisers left it: scored (or where it is), disqualified with their reason, hidden.
function standing(submission) {
  const status = document.createElement("span");
  status.className = `status ${submission.status}`;
  status.textContent = FINAL.includes(submission.status) ? submission.status : `${submission.status} ${submission.progress}%`;
  if (submission.error) status.title = submission.error;
  const sanctions = [
    submission.disqualified && `disqualified by an organiser${submission.disqualified_reason ? `: ${submission.disqualified_reason}` : ""}`,
    submission.admin_hidden && "hidden by an organiser",
    submission.hidden && "hidden by your team",
  ].filter(Boolean);
  const element = document.createElement("span");
  element.append(status);
  for (const text of sanctions) element.append(Object.assign(document.createElement("span"), { className: "sanction", textContent: text }));
  return element;
}

// Whether the board shows it (the API answers with the board's own choice), and the way to make it final.
function onBoard(submission, versions) {
  const shown = submission.on_leaderboard;
  const element = document.createElement("span");
  const why = submission.selected ? "your final entry" : "your best";
  if (shown.length === versions.length) element.append(`✓ shown, ${why}`);
  else if (shown.length) element.append(`✓ shown under ${shown.map((v) => `${PAGE.score_labels[v]} ${v}`).join(", ")}, ${why} there`);
  else if (submission.selected) element.append(Object.assign(document.createElement("span"), {
    className: "sanction", textContent: "final, but not shown: the board shows your best other entry",
  }));
  if (!submission.selected && submission.status === "scored") {
    if (submission.final_refusal === null) {
      element.append(button("make final", () => edit(submission.id, { selected: true }), "show this entry on the leaderboard, whatever its score"));
    } else if (!shown.length) {
      element.append(Object.assign(document.createElement("span"), { className: "note", textContent: "cannot be final" }));
    }
  }
  return element;
}

// The score columns of a phase: its versions, newest first, each two-stage one followed by its two stages.
function scoreColumns(versions) {
  return [...versions].reverse().flatMap((version) => {
    const name = `${PAGE.score_labels[version]} ${version}`;
    const score = { title: name, value: (s) => scoreOf(s, version) };
    if (!PAGE.two_stage_versions.includes(version)) return [score];
    const stage = (key) => (s) => (s.results?.[version]?.all || {})[key];
    return [
      score,
      { title: "Stage 1", value: stage("stage_one_score"), hint: `${name}, stage one: the logged frames, mean over groups` },
      { title: "Stage 2", value: stage("stage_two_score"), hint: `${name}, stage two: the synthetic successors, weighted` },
    ];
  });
}

function historyTable(phase, versions, submissions) {
  const section = document.createElement("section");
  section.className = "history-phase";
  const split = submissions[0].split;
  const title = Object.assign(document.createElement("h3"), { textContent: `Phase ${phase ?? "none"}` });
  title.append(Object.assign(document.createElement("small"), {
    textContent: ` split ${split}${versions.some((v) => PAGE.two_stage_versions.includes(v)) ? ", two stages" : ""} · ${counted(submissions.length, "entry", "entries")}`,
  }));
  const table = document.createElement("table");
  table.className = "board stack history";
  const columns = scoreColumns(versions);
  const head = table.createTHead().insertRow();
  for (const [name, hint] of [["Id"], ["Method"], ["Status"], ...columns.map((c) => [c.title, c.hint]), ["Submitted (UTC)"], ["On the leaderboard"], ["Actions"]]) {
    head.append(Object.assign(document.createElement("th"), { scope: "col", textContent: name, title: hint || "" }));
  }
  for (const th of [...head.cells].slice(3, 3 + columns.length)) th.className = "num";
  const body = table.createTBody();
  for (const submission of submissions) {
    const row = body.insertRow();
    const link = document.createElement("a");
    link.href = `/submissions/${submission.id}`;
    link.textContent = submission.id;
    cell(row, link);
    cell(row, submission.method);
    cell(row, standing(submission));
    for (const column of columns) cell(row, pct(column.value(submission)), "num");
    cell(row, when(submission.submitted_at));
    cell(row, onBoard(submission, versions));
    const actions = document.createElement("span");
    actions.append(
      button("edit", () => openEditor(submission), "edit the method name, authors and links"),
      button(submission.hidden ? "show" : "hide", () => edit(submission.id, { hidden: !submission.hidden }),
        submission.hidden ? "show it on the leaderboard again" : "keep it off the leaderboard"),
    );
    cell(row, actions);
  }
  const scroll = Object.assign(document.createElement("div"), { className: "scroll" });
  scroll.append(table);
  section.append(title, scroll);
  return section;
}

// One table per phase, the phase of the newest upload first, each with its own versions as columns.
async function loadHistory() {
  const [submissions, phases] = await Promise.all([api("GET", "/submissions"), api("GET", "/phases")]);
  const versionsOf = Object.fromEntries(phases.map((phase) => [phase.name, phase.versions]));
  const byPhase = new Map();
  for (const submission of submissions) {
    if (!byPhase.has(submission.phase)) byPhase.set(submission.phase, []);
    byPhase.get(submission.phase).push(submission);
  }
  $("#history").replaceChildren(...[...byPhase].map(([phase, rows]) => historyTable(phase, versionsOf[phase] || PAGE.versions, rows)));
  if (!submissions.length) $("#history").append(Object.assign(document.createElement("p"), { className: "empty", textContent: "No submission yet." }));
}

if (token()) showTeam().catch(() => sessionStorage.removeItem(TOKEN_KEY));
