// Admin dashboard: every read and action goes through the admin REST API with the token typed in,
// kept in sessionStorage only (gone when the tab closes).
"use strict";

const API = "/api/v1/admin";
const $ = (selector) => document.querySelector(selector);
const token = () => sessionStorage.getItem("navsim-lb-admin-token") || "";

async function call(method, path, body) {
  const response = await fetch(API + path, {
    method,
    headers: { Authorization: `Bearer ${token()}`, ...(body ? { "Content-Type": "application/json" } : {}) },
    body: body ? JSON.stringify(body) : undefined,
  });
  if (!response.ok) {
    const detail = (await response.json().catch(() => ({}))).detail || response.statusText;
    throw new Error(`${response.status}: ${typeof detail === "string" ? detail : JSON.stringify(detail)}`);
  }
  return response;
}

function cell(row, content) {
  const td = row.insertCell();
  if (content instanceof Node) td.append(content); else td.textContent = content ?? "";
  return td;
}

function button(label, action) {
  const element = document.createElement("button");
  element.textContent = label;
  element.addEventListener("click", async () => {
    try { await action(); await refresh(); } catch (error) { say(error.message); }
  });
  return element;
}

function actions(...buttons) {
  const span = document.createElement("span");
  span.append(...buttons.filter(Boolean));
  return span;
}

const say = (text) => { $("#message").textContent = text; };
const pct = (value) => (value === null || value === undefined ? "–" : (100 * value).toFixed(1));

function fillTeams(teams) {
  const body = $("#teams tbody");
  body.replaceChildren();
  for (const team of teams) {
    const row = body.insertRow();
    [team.id, team.name, team.affiliation, team.members.join(", "), team.approval].forEach((v) => cell(row, v));
    cell(row, actions(
      team.approval !== "approved" && button("approve", () => call("POST", `/teams/${team.id}/approve`)),
      team.approval !== "rejected" && button("reject", () => call("POST", `/teams/${team.id}/reject`)),
      button("new token", async () => {
        const created = await (await call("POST", `/teams/${team.id}/tokens`, { name: "dashboard" })).json();
        window.prompt(`Token for ${team.name} (shown once):`, created.token);
      }),
    ));
  }
}

function fillSubmissions(submissions) {
  const body = $("#submissions tbody");
  body.replaceChildren();
  for (const s of submissions) {
    const row = body.insertRow();
    const v11 = (s.results["v1.1"] || {});
    const best = v11.public || v11.all;
    const flags = [s.baseline && "baseline", s.hidden && "hidden by team", s.admin_hidden && "hidden",
      s.disqualified && `disqualified: ${s.disqualified_reason}`, s.selected && "final", s.error_detail && s.error_detail]
      .filter(Boolean).join(" · ");
    [s.id, s.team, s.method, s.status + (s.error ? ` (${s.error})` : ""), `${s.progress}%`, best ? pct(best.score) : "–",
      flags, s.submitted_at.slice(0, 16).replace("T", " ")].forEach((v) => cell(row, v));
    const active = s.status === "queued" || s.status === "running";
    cell(row, actions(
      !active && button("re-run", () => call("POST", `/submissions/${s.id}/rerun`)),
      active && button("cancel", () => call("POST", `/submissions/${s.id}/cancel`)),
      button(s.admin_hidden ? "show" : "hide", () => call("POST", `/submissions/${s.id}/hide`, { hidden: !s.admin_hidden })),
      s.disqualified
        ? button("requalify", () => call("POST", `/submissions/${s.id}/disqualify`, { disqualified: false, reason: "lifted" }))
        : button("disqualify", async () => {
          const reason = window.prompt("Reason for the disqualification:");
          if (reason) await call("POST", `/submissions/${s.id}/disqualify`, { disqualified: true, reason });
        }),
    ));
  }
}

function fillAudit(entries) {
  const body = $("#audit tbody");
  body.replaceChildren();
  for (const e of entries) {
    const row = body.insertRow();
    [e.at.slice(0, 19).replace("T", " "), e.actor, e.action, `${e.target_type} ${e.target_id}`, JSON.stringify(e.details)]
      .forEach((v) => cell(row, v));
  }
}

async function refresh() {
  const [teams, submissions, audit] = await Promise.all(
    ["/teams", "/submissions?limit=200", "/audit?limit=100"].map(async (path) => (await call("GET", path)).json()),
  );
  fillTeams(teams);
  fillSubmissions(submissions);
  fillAudit(audit);
  $("#dashboard").hidden = false;
}

async function open() {
  if (!token()) return;
  try { await refresh(); say(""); } catch (error) { $("#dashboard").hidden = true; say(error.message); }
}

$("#login").addEventListener("submit", (event) => {
  event.preventDefault();
  sessionStorage.setItem("navsim-lb-admin-token", $("#token").value.trim());
  $("#token").value = "";
  open();
});
$("#logout").addEventListener("click", () => { sessionStorage.removeItem("navsim-lb-admin-token"); location.reload(); });

$("#rescore").addEventListener("submit", async (event) => {
  event.preventDefault();
  const version = new FormData(event.target).get("version");
  if (!window.confirm(`Re-run every scored entry and report rank changes under ${version}?`)) return;
  try {
    const started = await (await call("POST", "/rescore", { version })).json();
    $("#report").textContent = `rescore ${started.id}: ${started.queued} submissions queued; report: ${started.report}`;
    await refresh();
  } catch (error) { say(error.message); }
});

for (const element of document.querySelectorAll("[data-export]")) {
  element.addEventListener("click", async () => {
    const version = new FormData($("#rescore")).get("version");
    try {
      const format = element.dataset.export;
      const blob = await (await call("GET", `/export?format=${format}&version=${version}`)).blob();
      const link = Object.assign(document.createElement("a"), { href: URL.createObjectURL(blob), download: `leaderboard-${version}.${format}` });
      link.click();
      URL.revokeObjectURL(link.href);
    } catch (error) { say(error.message); }
  });
}

open();
