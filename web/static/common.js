// What every page script shares: the API with the page's token (a team's, or an organiser's on the admin
// console: the page's <meta name="token-key"> says which) kept in sessionStorage (gone when the tab closes),
// its errors, and small DOM and number helpers. Loaded before the page's own script.
"use strict";

const API = "/api/v1";
const TOKEN_KEY = document.querySelector('meta[name="token-key"]').content;
const $ = (selector) => document.querySelector(selector);
const token = () => sessionStorage.getItem(TOKEN_KEY) || "";
// One rule for every figure (server/numbers.py writes the same): a stored fraction in percent with one
// decimal, 100 × the float rounded by toFixed (halves away from zero), "–" when undefined.
function pct(value) {
  if (value === null || value === undefined || !Number.isFinite(value)) return "–";
  const text = (100 * value).toFixed(1);
  return text === "-0.0" ? "0.0" : text;
}
// A change in percentage points: "+1.2", "-0.4", "0.0".
const pointChange = (value) => { const text = pct(value); return text === "–" || text.startsWith("-") || text === "0.0" ? text : `+${text}`; };
// "1 entry", "2 entries".
const counted = (count, singular, plural = `${singular}s`) => `${count} ${count === 1 ? singular : plural}`;
const when = (text) => (text ? text.slice(0, 16).replace("T", " ") : "–");

class ApiError extends Error {
  constructor(status, body) {
    super(typeof body.detail === "string" ? body.detail : `${status}`);
    this.status = status;
    this.body = body;
  }
}

async function api(method, path, { json, form, bearer = token() } = {}) {
  const headers = { Authorization: `Bearer ${bearer}` };
  if (json) headers["Content-Type"] = "application/json";
  const response = await fetch(API + path, { method, headers, body: json ? JSON.stringify(json) : form });
  const body = await response.json().catch(() => ({}));
  if (!response.ok) throw new ApiError(response.status, body);
  return body;
}

function cell(row, content, className) {
  const td = row.insertCell();
  if (content instanceof Node) td.append(content); else td.textContent = content ?? "";
  if (className) td.className = className;
  // A phone stacks the cells of a table.stack (style.css): each names its column.
  const header = row.closest("table")?.tHead?.rows[0]?.cells[td.cellIndex];
  if (header) td.dataset.label = header.textContent.trim();
  return td;
}

function button(label, action, title) {
  const element = document.createElement("button");
  element.type = "button";
  element.textContent = label;
  if (title) element.title = title;
  element.addEventListener("click", action);
  return element;
}

function describeError(error) {
  if (!(error instanceof ApiError)) return `The server could not be reached (${error.message}).`;
  if (error.status === 401) return "This token is not valid (revoked, expired or mistyped).";
  return error.message;
}
