// Admin console: every read and action goes through the admin REST API with the organiser's token
// (common.js keeps it in this tab only). The queue, the workers and the submissions refresh on their own
// every few seconds while the tab is visible; the rest after each action.
"use strict";

const LIVE_EVERY_MS = 3000;
const ACTIVE = ["queued", "running"];
const state = { submissions: [], teams: [], phases: [], audit: [], team: null };

function age(since) {
  const seconds = Math.max(0, (Date.now() - Date.parse(since)) / 1000);
  if (seconds < 90) return `${Math.round(seconds)} s`;
  if (seconds < 5400) return `${Math.round(seconds / 60)} min`;
  return `${(seconds / 3600).toFixed(1)} h`;
}

// A new token's secret, shown once in a dialog with a copy button; gone from the page when it closes.
async function showSecret(title, text, secret) {
  const dialog = $("#token-dialog");
  $("#token-title").textContent = title;
  $("#token-text").textContent = text;
  $("#token-value").textContent = secret;
  $("#token-copied").textContent = "";
  dialog.showModal();
  await new Promise((resolve) => dialog.addEventListener("close", resolve, { once: true }));
  $("#token-value").textContent = "";
}

$("#copy-token").addEventListener("click", async () => {
  const secret = $("#token-value").textContent;
  let copied = false;
  try {
    await navigator.clipboard.writeText(secret);
    copied = true;
  } catch {  // no clipboard API (a page served over plain HTTP to another host): select it and copy
    const range = document.createRange();
    range.selectNodeContents($("#token-value"));
    getSelection().removeAllRanges();
    getSelection().addRange(range);
    copied = document.execCommand("copy");
  }
  $("#token-copied").textContent = copied ? "Copied. It is not shown again: store it now."
    : "Selected: copy it with Ctrl+C (⌘C). It is not shown again.";
});

const cancelling = (s) => ({
  title: `Cancel submission ${s.id}?`,
  text: `${s.team}'s “${s.method}” stops being scored and is refunded to the team's quota. It cannot be resumed: a re-run would score it from the start.`,
  confirm: "Cancel it",
});

function progress(submission) {
  const bar = document.createElement("progress");
  bar.max = 100;
  bar.value = submission.progress;
  bar.title = `${submission.progress}%`;
  return group(bar, ` ${submission.progress}%`);
}

function fillQueue() {
  const body = $("#queue tbody");
  body.replaceChildren();
  const active = state.submissions.filter((s) => ACTIVE.includes(s.status)).sort((a, b) => a.id - b.id);
  for (const s of active) {
    const row = body.insertRow();
    [s.id, s.team, s.method, s.status, age(s.queued_at)].forEach((v, i) => cell(row, v, i === 4 ? "num" : ""));
    cell(row, progress(s));
    cell(row, s.worker || "–");
    cell(row, s.attempts, "num");
    cell(row, act("cancel", cancelling(s), () => api("POST", `${ADMIN}/submissions/${s.id}/cancel`)));
  }
  if (!active.length) cell(body.insertRow(), "Nothing is waiting.", "empty").colSpan = 9;
}

async function fillWorkers() {
  const list = $("#workers");
  const health = await fetch(`${API}/health`).then((response) => response.json()).catch(() => null);
  const items = [];
  if (!health) items.push("The API's health check does not answer.");
  else {
    items.push(`Broker: ${health.broker.ok ? "answers" : `does not answer (${health.broker.detail})`}.`);
    const workers = health.workers;
    const how = workers.detail.includes("heartbeat") ? "alive (heartbeats in the database)" : "answering a ping";
    if (workers.ok === null) items.push(`Workers: unknown (${workers.detail}).`);
    else items.push(workers.count ? `Workers ${how}: ${workers.names.join(", ")}.` : `No worker is ${how} (${workers.detail}).`);
  }
  // Every transport: the workers that claimed the runs in progress.
  const holding = new Map();
  for (const s of state.submissions.filter((s) => s.status === "running" && s.worker)) {
    holding.set(s.worker, [...(holding.get(s.worker) || []), s.id]);
  }
  for (const [worker, ids] of holding) items.push(`${worker} is scoring ${ids.length === 1 ? "submission" : "submissions"} ${ids.join(", ")}.`);
  if (!holding.size) items.push("No worker holds a run at the moment.");
  list.replaceChildren(...items.map((text) => Object.assign(document.createElement("li"), { textContent: text })));
}

function fillSubmissions() {
  const body = $("#submissions tbody");
  body.replaceChildren();
  const failedOnly = $("#failed-only").checked;
  for (const s of state.submissions.filter((s) => !failedOnly || s.status === "failed")) {
    const row = body.insertRow();
    // The score under v1.1, or under the split's own version (a two-stage split has only its two-stage one).
    const version = "v1.1" in s.results ? "v1.1" : Object.keys(s.results)[0];
    const results = s.results[version] || {};
    const best = results.public || results.all;
    const flags = [s.baseline && "baseline", s.hidden && "hidden by team", s.admin_hidden && "hidden",
      s.disqualified && `disqualified: ${s.disqualified_reason}`, s.selected && "final"].filter(Boolean).join(" · ");
    const status = group(Object.assign(document.createElement("span"), { className: `status ${s.status}`, textContent: s.status }));
    if (s.error) status.append(` · ${s.error}`);
    if (s.error_detail) {
      const details = document.createElement("details");
      details.append(Object.assign(document.createElement("summary"), { textContent: "detail" }),
        Object.assign(document.createElement("pre"), { textContent: s.error_detail }));
      status.append(details);
    }
    const link = Object.assign(document.createElement("a"), { href: `/submissions/${s.id}`, textContent: s.id });
    cell(row, s.baseline ? String(s.id) : link);
    [s.team, s.method].forEach((v) => cell(row, v));
    cell(row, status);
    cell(row, `${s.progress}%`, "num");
    cell(row, best ? group(pct(best.score), Object.assign(document.createElement("small"), { className: "version", textContent: version })) : "–", "num");
    cell(row, flags);
    cell(row, when(s.submitted_at));
    const active = ACTIVE.includes(s.status);
    const path = `${ADMIN}/submissions/${s.id}`;
    cell(row, group(
      !active && act("re-run", {
        title: `Re-run submission ${s.id}?`,
        text: `${entryName(s)} is scored again from the start under a new run; its current results stay shown until the new run is scored.`,
        confirm: "Re-run it",
      }, () => api("POST", `${path}/rerun`), "score it again under a new run"),
      active && act("cancel", cancelling(s), () => api("POST", `${path}/cancel`)),
      ...moderation(s),
    ));
  }
}

function fillTeams() {
  const body = $("#teams tbody");
  body.replaceChildren();
  for (const team of state.teams) {
    const row = body.insertRow();
    [team.id, team.name, team.affiliation, team.members.join(", ")].forEach((v) => cell(row, v));
    cell(row, Object.assign(document.createElement("span"), { className: `status ${team.approval}`, textContent: team.approval }));
    cell(row, group(
      team.approval !== "approved" && act("approve", {
        title: `Approve team ${team.name}?`,
        text: "Its tokens may upload submissions from now on, within the phase's quotas.",
        confirm: "Approve it",
      }, () => api("POST", `${ADMIN}/teams/${team.id}/approve`)),
      team.approval !== "rejected" && act("reject", {
        title: `Reject team ${team.name}?`,
        text: "Its tokens can no longer upload; its entries stay as they are (hide or disqualify them one by one).",
        confirm: "Reject it",
      }, () => api("POST", `${ADMIN}/teams/${team.id}/reject`)),
      button("tokens and quotas", () => openTeam(team)),
    ));
  }
}

async function openTeam(team) {
  state.team = team;
  $("#team-detail").hidden = false;
  $("#team-detail-title").textContent = `${team.name}: tokens and quotas`;
  const tokens = await api("GET", `${ADMIN}/teams/${team.id}/tokens`);
  const body = $("#tokens tbody");
  body.replaceChildren();
  for (const t of tokens) {
    const row = body.insertRow();
    [t.id, t.name, t.prefix, when(t.created_at), when(t.last_used_at)].forEach((v) => cell(row, v));
    cell(row, t.revoked_at ? `revoked ${when(t.revoked_at)}` : t.expires_at ? `expires ${when(t.expires_at)}` : "active");
    cell(row, t.revoked_at ? "" : act("revoke", {
      title: `Revoke token ${t.prefix}… of ${team.name}?`,
      text: "Whatever uses it is refused from now on. A revoked token cannot be restored; the team needs a new one.",
      confirm: "Revoke it",
    }, async () => {
      await api("DELETE", `${ADMIN}/tokens/${t.id}`);
      await openTeam(team);
    }));
  }
  const add = body.insertRow();
  cell(add, button("new token", async () => {
    try {
      const created = await api("POST", `${ADMIN}/teams/${team.id}/tokens`, { json: { name: "console" } });
      await openTeam(team);
      await showSecret(`New token for ${team.name}`, "Give it to the team. It is shown this once: the server keeps only its hash.", created.token);
    } catch (error) { say(describeError(error)); }
  })).colSpan = 7;
  $("#quota-phase").replaceChildren(...state.phases.map((phase) => new Option(phase.name, phase.name)));
}

$("#quota").addEventListener("submit", async (event) => {
  event.preventDefault();
  const data = new FormData(event.target);
  const number = (name) => (data.get(name) === "" ? null : Number(data.get(name)));
  const shown = (name) => (data.get(name) === "" ? "the phase default" : data.get(name));
  const answer = await ask({
    title: `Set the quotas of ${state.team.name} in ${data.get("phase")}?`,
    text: `Per day: ${shown("per_day")}; total: ${shown("total")}; in flight: ${shown("in_flight")}. They apply to the team's next upload.`,
    confirm: "Set them",
  });
  if (answer === null) return;
  try {
    await api("PUT", `${ADMIN}/teams/${state.team.id}/quotas`, {
      json: { phase: data.get("phase"), per_day: number("per_day"), total: number("total"), in_flight: number("in_flight") },
    });
    say(`Quotas of ${state.team.name} in ${data.get("phase")} set.`);
    await refresh();
  } catch (error) { say(describeError(error)); }
});

function fillAudit() {
  const body = $("#audit tbody");
  body.replaceChildren();
  const filter = $("#audit-filter").value.trim().toLowerCase();
  for (const e of state.audit) {
    const text = [e.actor, e.action, e.target_type, e.target_id].join(" ").toLowerCase();
    if (filter && !text.includes(filter)) continue;
    const row = body.insertRow();
    [e.at.slice(0, 19).replace("T", " "), e.actor, e.action, `${e.target_type} ${e.target_id}`].forEach((v) => cell(row, v));
    cell(row, detailList(e.details), "details");
  }
}

// An audit entry's details as lines a person reads ("reason: …"), wrapping where a value is long.
async function refreshLive() {
  let integrity;
  // The checks run after every scored run: new flags show up in the nav while the console is open.
  [state.submissions, integrity] = await Promise.all([api("GET", `${ADMIN}/submissions?limit=300`), api("GET", `${ADMIN}/integrity`)]);
  integrityLink($("#integrity-link"), integrity.checks);
  fillQueue();
  fillSubmissions();
  await fillWorkers();
  $("#updated").textContent = `updated ${new Date().toLocaleTimeString()}`;
}

async function refresh() {
  [state.teams, state.audit, state.phases] = await Promise.all([
    api("GET", `${ADMIN}/teams`), api("GET", `${ADMIN}/audit?limit=300`), api("GET", "/phases"),
  ]);
  fillTeams();
  fillAudit();
  await refreshLive();
  $("#dashboard").hidden = false;
}

async function open() {
  if (!token()) return;
  try { await refresh(); say(""); } catch (error) { $("#dashboard").hidden = true; say(describeError(error)); return; }
  setInterval(() => {
    if (document.visibilityState === "visible") refreshLive().catch((error) => say(describeError(error)));
  }, LIVE_EVERY_MS);
}

$("#login").addEventListener("submit", (event) => {
  event.preventDefault();
  sessionStorage.setItem(TOKEN_KEY, $("#token").value.trim());
  $("#token").value = "";
  open();
});
$("#logout").addEventListener("click", () => { sessionStorage.removeItem(TOKEN_KEY); location.reload(); });
$("#failed-only").addEventListener("change", fillSubmissions);
$("#audit-filter").addEventListener("input", fillAudit);

$("#rescore").addEventListener("submit", async (event) => {
  event.preventDefault();
  const form = new FormData(event.target);
  const version = form.get("version");
  const compareWith = form.get("compare_with") || null;
  const answer = await ask({
    title: `Rescore every entry under ${version}?`,
    text: `Every scored entry of the phase, baselines included, is re-run; the board shows the old results until each new run is scored, and a report compares the ranks under ${compareWith || version} before with those after.`,
    confirm: "Rescore all",
  });
  if (answer === null) return;
  try {
    const started = await api("POST", `${ADMIN}/rescore`, { json: { version, compare_with: compareWith } });
    const link = Object.assign(document.createElement("a"), { href: `/admin/rescores/${started.id}`, textContent: "open its rank-change report" });
    $("#report").replaceChildren(`Rescore ${started.id}: ${started.queued} submissions queued; `, link, ".");
    await refresh();
  } catch (error) { say(describeError(error)); }
});

for (const element of document.querySelectorAll("[data-export]")) {
  element.addEventListener("click", async () => {
    const version = new FormData($("#rescore")).get("version");
    const format = element.dataset.export;
    try {
      const response = await fetch(`${API}${ADMIN}/export?format=${format}&version=${version}`, { headers: { Authorization: `Bearer ${token()}` } });
      if (!response.ok) throw new ApiError(response.status, await response.json().catch(() => ({})));
      const link = Object.assign(document.createElement("a"), { href: URL.createObjectURL(await response.blob()), download: `leaderboard-${version}.${format}` });
      link.click();
      URL.revokeObjectURL(link.href);
    } catch (error) { say(describeError(error)); }
  });
}

open();
