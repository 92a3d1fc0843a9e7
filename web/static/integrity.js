// Integrity checks (organisers only): run the checks of a split, read each flag with its evidence, and decide
// with the console's moderation actions (console.js), each asking first. Follows a running check until done.
"use strict";

const FOLLOW_EVERY_MS = 2000;
const KINDS = { leaked_log: "Leaked log", near_duplicate: "Near-identical entries", probing: "Probing the hidden set" };
let following = null;
let fresh = null;  // the keys of the flags new to this organiser since this page was opened

function evidence(flag) {
  const details = document.createElement("details");
  details.append(Object.assign(document.createElement("summary"), { textContent: "evidence" }), detailList(flag.evidence));
  return group(Object.assign(document.createElement("p"), { textContent: flag.summary, className: "finding" }), details);
}

function submissionLink(id) {
  return Object.assign(document.createElement("a"), { href: `/submissions/${id}`, textContent: id });
}

function report(check) {
  const section = document.createElement("section");
  section.className = "integrity-check";
  const title = document.createElement("h2");
  title.textContent = `Split ${check.split}`;
  const facts = document.createElement("p");
  facts.className = "facts";
  if (check.error) facts.textContent = `The check failed: ${check.error}`;
  else if (!check.finished_at) facts.textContent = `Running since ${when(check.started_at)} UTC…`;
  else {
    const skipped = check.skipped.length ? `; ${counted(check.skipped.length, "submission")} could not be read` : "";
    facts.textContent = `Checked ${when(check.finished_at)} UTC: ${counted(check.entries, "entry", "entries")} read${skipped}; `
      + (check.flags.length ? `${counted(check.flags.length, "flag")}.` : "nothing to flag.");
  }
  section.append(title, facts);
  if (!check.flags.length) return section;
  const table = document.createElement("table");
  table.className = "board stack flags";
  table.createCaption().textContent = "Flags, each with its evidence: none acts by itself";
  const head = table.createTHead().insertRow();
  for (const name of ["Kind", "Submission", "Team", "Method", "Finding", "State", "Decide"]) {
    head.append(Object.assign(document.createElement("th"), { scope: "col", textContent: name }));
  }
  const body = table.createTBody();
  for (const flag of check.flags) {
    const row = body.insertRow();
    const kind = group(KINDS[flag.kind] || flag.kind);
    if (fresh.has(flagKey(flag))) {
      row.classList.add("fresh");
      kind.append(" ", badge("new", "not seen before in this browser", "alert"));
    }
    cell(row, kind, "kind");
    const ids = group(submissionLink(flag.submission_id));
    if (flag.other_submission_id) ids.append(" copies ", submissionLink(flag.other_submission_id));
    cell(row, ids);
    cell(row, flag.team);
    cell(row, flag.method);
    cell(row, evidence(flag), "evidence");
    cell(row, [flag.admin_hidden && "hidden", flag.disqualified && "disqualified"].filter(Boolean).join(" · ") || "shown");
    cell(row, group(...moderation({ ...flag, id: flag.submission_id, disqualified_reason: "" })));
  }
  const scroll = document.createElement("div");
  scroll.className = "scroll";
  scroll.append(table);
  section.append(scroll);
  return section;
}

async function refresh() {
  const { checks } = await api("GET", `${ADMIN}/integrity`);
  fresh = new Set([...(fresh || []), ...newFlags(checks).map(flagKey)]);
  markFlagsSeen(checks);
  $("#reports").replaceChildren(...checks.map(report));
  if (!checks.length) $("#reports").textContent = "No check has run yet.";
  $("#checks").hidden = false;
  const running = checks.some((check) => !check.finished_at && !check.error);
  if (running && !following) following = setTimeout(() => { following = null; refresh().catch((error) => say(describeError(error))); }, FOLLOW_EVERY_MS);
}

async function open() {
  if (!token()) { $("#login").hidden = false; return; }
  try {
    const splits = await api("GET", "/splits");
    $("#split").replaceChildren(new Option("every split", ""), ...splits.map((split) => new Option(split.name, split.name)));
    await refresh();
    $("#login").hidden = true;
    say("");
  } catch (error) {
    $("#login").hidden = false;
    say(describeError(error));
  }
}

$("#login").addEventListener("submit", (event) => {
  event.preventDefault();
  sessionStorage.setItem(TOKEN_KEY, $("#token").value.trim());
  $("#token").value = "";
  open();
});

$("#run").addEventListener("submit", async (event) => {
  event.preventDefault();
  const split = $("#split").value || null;
  try {
    await api("POST", `${ADMIN}/integrity/checks`, { json: { split } });
    say(`Checking ${split ? `split ${split}` : "every split"}; the flags appear here when it is done.`);
    await refresh();
  } catch (error) { say(describeError(error)); }
});

open();
