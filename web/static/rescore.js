// Rank-change report of a rescore, read with the organiser's token; it refreshes until every run is done.
"use strict";

const RESCORE = $("#message").dataset.rescore;
const FOLLOW_EVERY_MS = 3000;

async function show() {
  if (!token()) {
    $("#message").textContent = "Open the admin console with your token first; this page reads it from there.";
    return;
  }
  let report;
  try {
    report = await api("GET", `/admin/rescores/${RESCORE}`);
  } catch (error) {
    $("#message").textContent = describeError(error);
    return;
  }
  const tau = report.kendall_tau === null ? "–" : report.kendall_tau.toFixed(3);
  const compared = report.before_version === report.version ? ""
    : ` (ranks before: ${report.before_score_label} ${report.before_version})`;
  $("#summary").textContent = `${report.phase}, ${report.score_label} ${report.version}${compared}, ${report.subset} tokens · ${counted(report.submissions, "submission")} ` +
    `re-run, ${report.pending} still running, ${report.failed} failed · Kendall's tau ${tau} over ` +
    `${counted(report.entries, "entry", "entries")} · ${report.complete ? "complete" : "in progress"}`;
  const body = $("#moved tbody");
  body.replaceChildren();
  for (const move of report.moved) {
    const row = body.insertRow();
    cell(row, move.team);
    cell(row, move.method);
    for (const value of [move.rank_before, move.rank_after]) cell(row, value, "num");
    for (const value of [move.score_before, move.score_after]) cell(row, pct(value), "num");
  }
  if (!report.moved.length) cell(body.insertRow(), "No rank changed.", "empty").colSpan = 6;
  $("#entered-left").textContent = `Entered: ${report.entered.join(", ") || "none"} · left: ${report.left.join(", ") || "none"}`;
  $("#report").hidden = false;
  $("#message").textContent = "";
  if (!report.complete) setTimeout(show, FOLLOW_EVERY_MS);
}

show();
