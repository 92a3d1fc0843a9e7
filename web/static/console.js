// What the organisers' pages share: the confirmation every action that changes or hides data asks first (the
// #confirm dialog, templates/_confirm.html), the moderation of a submission (hide, disqualify, and back), and
// a record's details as a readable list. Each page defines `refresh()`, called after an action, and has a
// #message line. Loaded after common.js.
"use strict";

const ADMIN = "/admin";
const say = (text) => { $("#message").textContent = text; };

// Every action that changes or hides data asks first, saying what it will do; with `reason`, it asks for one
// (the team reads it). Answers the reason ("" without one), or null when the organiser keeps things as they are.
async function ask({ title, text, confirm, reason = false }) {
  const dialog = $("#confirm");
  $("#confirm-title").textContent = title;
  $("#confirm-text").textContent = text;
  $("#confirm-ok").textContent = confirm;
  $("#confirm-reason-label").hidden = !reason;
  $("#confirm-reason").required = reason;
  $("#confirm-reason").value = "";
  dialog.returnValue = "";
  dialog.showModal();
  await new Promise((resolve) => dialog.addEventListener("close", resolve, { once: true }));
  return dialog.returnValue === "confirm" ? $("#confirm-reason").value.trim() : null;
}

function act(label, question, action, title) {
  return button(label, async () => {
    const reason = await ask(question);
    if (reason === null) return;
    try { await action(reason); await refresh(); } catch (error) { say(describeError(error)); }
  }, title);
}

function group(...elements) {
  const span = document.createElement("span");
  span.append(...elements.filter(Boolean));
  return span;
}

const entryName = (s) => `${s.team}'s “${s.method}”`;

// The hide/show and disqualify/requalify buttons of a submission (`s` names id, team, method, admin_hidden,
// disqualified and disqualified_reason), each asking first.
function moderation(s) {
  const path = `${ADMIN}/submissions/${s.id}`;
  const entry = entryName(s);
  return [
    s.admin_hidden
      ? act("show", {
        title: `Show submission ${s.id} again?`,
        text: `${entry} may return to the leaderboard, and its team may make it final again.`,
        confirm: "Show it",
      }, () => api("POST", `${path}/hide`, { json: { hidden: false } }))
      : act("hide", {
        title: `Hide submission ${s.id}?`,
        text: `${entry} leaves the leaderboard. Its team sees that an organiser hid it, and cannot show it or make it final.`,
        confirm: "Hide it",
      }, () => api("POST", `${path}/hide`, { json: { hidden: true } })),
    s.disqualified
      ? act("requalify", {
        title: `Lift the disqualification of submission ${s.id}?`,
        text: `${entry} may return to the leaderboard (reason given: ${s.disqualified_reason || "none"}).`,
        confirm: "Lift it",
      }, () => api("POST", `${path}/disqualify`, { json: { disqualified: false, reason: "lifted" } }))
      : act("disqualify", {
        title: `Disqualify submission ${s.id}?`,
        text: `${entry} leaves the leaderboard and cannot be its team's final entry. The team reads the reason you give.`,
        confirm: "Disqualify it",
        reason: true,
      }, (reason) => api("POST", `${path}/disqualify`, { json: { disqualified: true, reason } })),
  ];
}

// A value in words: lists joined, records as "key value" pairs, nothing as "–".
function shownValue(value) {
  if (value === null || value === undefined) return "–";
  if (Array.isArray(value)) return value.map(shownValue).join("; ") || "none";
  if (typeof value === "object") return Object.entries(value).map(([key, item]) => `${key.replaceAll("_", " ")} ${shownValue(item)}`).join(", ");
  return String(value);
}

function detailList(details) {
  if (!Object.keys(details).length) return "–";
  const list = document.createElement("dl");
  for (const [key, value] of Object.entries(details)) {
    list.append(Object.assign(document.createElement("dt"), { textContent: key.replaceAll("_", " ") }),
      Object.assign(document.createElement("dd"), { textContent: shownValue(value) }));
  }
  return list;
}

// Integrity flags an organiser has not seen yet on the integrity page, in this browser (localStorage: it
// outlives the tab), whose entry is still on the board: the count the console's nav shows. A flag is the same
// flag from one check to the next while it names the same kind and submissions.
const SEEN_FLAGS_KEY = "navsim-lb-integrity-seen";
const flagKey = (flag) => `${flag.kind}:${flag.submission_id}:${flag.other_submission_id ?? ""}`;
function seenFlags() {
  try { return new Set(JSON.parse(localStorage.getItem(SEEN_FLAGS_KEY) || "[]")); } catch { return new Set(); }
}
const newFlags = (checks, seen = seenFlags()) => checks.flatMap((check) => check.flags)
  .filter((flag) => !seen.has(flagKey(flag)) && !flag.admin_hidden && !flag.disqualified);
// What is seen is what the page shows: flags gone from every check are forgotten.
function markFlagsSeen(checks) {
  localStorage.setItem(SEEN_FLAGS_KEY, JSON.stringify(checks.flatMap((check) => check.flags).map(flagKey)));
}

function badge(text, title, kind = "") {
  return Object.assign(document.createElement("span"), { className: `badge ${kind}`.trim(), textContent: text, title });
}

// The nav link to the integrity page: how many flags are new, and whether a split's last check failed.
function integrityLink(link, checks) {
  const fresh = newFlags(checks).length;
  const failed = checks.filter((check) => check.error).length;
  const all = checks.reduce((sum, check) => sum + check.flags.length, 0);
  link.replaceChildren("Integrity checks");
  if (fresh) link.append(" ", badge(`${fresh} new`, `${counted(fresh, "flag")} you have not opened yet, of ${all}`, "alert"));
  else if (all) link.append(" ", badge(`${all}`, `${counted(all, "flag")}, all seen`));
  if (failed) link.append(" ", badge("check failed", `the last check of ${counted(failed, "split")} failed: open it to read why`, "alert"));
}
