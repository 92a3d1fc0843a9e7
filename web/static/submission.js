// Submission page: the per-metric breakdown next to the phase's baselines, histograms of per-token PDMS
// and of each subscore (in %, as the tables), the tokens that lost most, the drill-down picture of a token,
// and a per-token diff with another of the team's submissions, a published entry or a baseline. Everything
// comes from the API (common.js); histograms are drawn as inline SVG. The address keeps the chosen version,
// subset, token and comparison (?version=&subset=&token=&compare=), so that any view can be linked to.
"use strict";

const PAGE = JSON.parse($("#page-data").textContent);
const LABELS = PAGE.labels; // devkit column -> short name
const WORST_SHOWN = 15;
const DIFF_PAGE = 25;
const PHONE = window.matchMedia("(max-width: 700px)");
// The owning team reads it with its token; an organiser who opened the admin console, with the admin's;
// anyone else, once the entry is published (its phase has closed), through the public routes.
const ADMIN_TOKEN_KEY = "navsim-lb-admin-token";
const mode = () => (token() ? "team" : sessionStorage.getItem(ADMIN_TOKEN_KEY) ? "admin" : "public");
const bearer = () => (mode() === "admin" ? sessionStorage.getItem(ADMIN_TOKEN_KEY) : token());
const scoped = (path) => ({ team: path, admin: `/admin${path}`, public: path.replace("/submissions/", "/published/") })[mode()];
const read = (path) => api("GET", scoped(path), { bearer: bearer() });
const ADDRESS = new URLSearchParams(location.search);
const state = {
  submission: null,
  version: PAGE.versions.includes(ADDRESS.get("version")) ? ADDRESS.get("version") : PAGE.default_version,
  subset: ADDRESS.get("subset"),
  token: ADDRESS.get("token"),
  compare: ADDRESS.get("compare") || "",
  rows: {},
  others: [],
  pages: { better: 0, worse: 0 },
};

// The address of this page with the current choices, and `changes` over them.
function address(changes = {}, submissionId = PAGE.submission_id) {
  const chosen = { version: state.version, subset: state.subset, token: state.token, compare: state.compare, ...changes };
  const query = new URLSearchParams(Object.entries(chosen).filter(([, value]) => value));
  return `/submissions/${submissionId}?${query}`;
}
const remember = () => history.replaceState(null, "", address());

// A token as a link to its drill-down: on this page it draws the scene in place; the address opens it too.
function sceneLink(token, submissionId = PAGE.submission_id, text = token) {
  const link = document.createElement("a");
  link.href = `${address({ token, compare: submissionId === PAGE.submission_id ? state.compare : "" }, submissionId)}#scene-title`;
  link.textContent = text;
  link.className = "token-link";
  link.title = submissionId === PAGE.submission_id ? "draw this scene" : "open this token on that entry's page";
  if (submissionId === PAGE.submission_id) {
    link.addEventListener("click", (event) => {
      if (event.ctrlKey || event.metaKey || event.shiftKey) return;
      event.preventDefault();
      showScene(token);
    });
  }
  return link;
}

const label = (column) => (column === "score" ? PAGE.score_labels[state.version] : LABELS[column] || column);
const defined = (value) => value !== null && value !== undefined;
const FILTER_SHOWN = 15;
const BREAKDOWN_CAPTION = $("#breakdown caption").textContent;
const columnsOf = (results) => Object.keys(results).filter((key) => key in LABELS && key !== "score");

function tab(text, current, action) {
  const link = document.createElement("a");
  link.href = "#";
  link.textContent = text;
  if (current) link.setAttribute("aria-current", "page");
  link.addEventListener("click", (event) => { event.preventDefault(); action(); });
  return link;
}

async function tokenRows(submissionId, version) {
  const key = `${submissionId}/${version}`;
  if (!(key in state.rows)) state.rows[key] = await read(`/submissions/${submissionId}/tokens?version=${version}`);
  return state.rows[key];
}

// Per token the mean over seeds, as the leaderboard averages seeds (an unscored token counts 0; an undefined
// value, v2.2's EC without the frame before, is left out, and null where no seed defines it). With it, the
// columns the human filter set to 1 and the agent's values before it (v2.2), over all seeds.
function perToken(rows, columns) {
  const tokens = new Map();
  for (const row of rows) {
    const entry = tokens.get(row.token) || { token: row.token, errors: [], sums: {}, counts: {}, overridden: new Set(), before: {} };
    if (!row.valid) entry.errors.push(row.error || "not scored");
    for (const column of ["score", ...columns]) {
      const value = row.valid ? row.metrics[column] : 0;
      if (!defined(value)) continue;
      entry.sums[column] = (entry.sums[column] || 0) + value;
      entry.counts[column] = (entry.counts[column] || 0) + 1;
    }
    const filter = (row.detail || {}).human_filter;
    for (const column of (filter && filter.overridden) || []) {
      entry.overridden.add(column);
      (entry.before[column] ||= []).push(filter.agent_before[column]);
    }
    tokens.set(row.token, entry);
  }
  for (const entry of tokens.values()) {
    entry.values = {};
    for (const column of ["score", ...columns]) {
      entry.values[column] = column in entry.counts ? entry.sums[column] / entry.counts[column] : null;
    }
  }
  return Array.from(tokens.values());
}

// "DAC counts 1 (yours 0)": what the filter did to a token's columns, for a person to read.
function overrides(entry) {
  return [...entry.overridden].map((column) => {
    const before = entry.before[column].reduce((a, b) => a + b, 0) / entry.before[column].length;
    return `${label(column)} counts 1 (yours ${pct(before)})`;
  }).join(" · ");
}

// Counts of per-token values (0-1) in `bins` equal bins, drawn in % as the tables show them; the text is
// sized for the width the grid gives a figure (at least 250 px), so it reads at 12 px or more.
function histogram(title, values, bins) {
  const width = 300, height = 140, left = 34, right = 10, top = 8, axis = 118;
  const counts = new Array(bins).fill(0);
  for (const value of values.filter(defined)) counts[Math.min(bins - 1, Math.max(0, Math.floor(value * bins)))] += 1;
  const most = Math.max(1, ...counts);
  const bar = (width - left - right) / bins;
  const range = (index) => `${Math.round((100 * index) / bins)}–${Math.round((100 * (index + 1)) / bins)} %`;
  const svg = document.createElementNS("http://www.w3.org/2000/svg", "svg");
  const add = (name, attributes, text) => {
    const element = document.createElementNS(svg.namespaceURI, name);
    for (const [key, value] of Object.entries(attributes)) element.setAttribute(key, value);
    if (text !== undefined) element.textContent = text;
    svg.append(element);
    return element;
  };
  svg.setAttribute("viewBox", `0 0 ${width} ${height}`);
  svg.setAttribute("role", "img");
  svg.setAttribute("aria-label", `${title}: ${counts.map((count, i) => `${count} tokens in ${range(i)}`).join(", ")}`);
  counts.forEach((count, index) => {
    const h = (count / most) * (axis - top);
    const rect = add("rect", {
      x: left + index * bar + 0.5, y: axis - h, width: Math.max(1, bar - 1), height: h,
      class: index === bins - 1 ? "bar full" : "bar",
    });
    const tip = document.createElementNS(svg.namespaceURI, "title");
    tip.textContent = `${count} token(s) in ${range(index)}`;
    rect.append(tip);
  });
  add("line", { x1: left, x2: width - right, y1: axis + 0.5, y2: axis + 0.5, class: "axis" });
  add("line", { x1: left - 0.5, x2: left - 0.5, y1: top, y2: axis, class: "axis" });
  for (const [at, text] of [[0, "0"], [0.5, "50"], [1, "100 %"]]) {
    const x = left + at * (width - left - right);
    add("text", { x, y: axis + 17, "text-anchor": at === 1 ? "end" : "middle" }, text);
  }
  for (const [y, text] of [[top + 10, String(most)], [axis, "0"]]) add("text", { x: left - 5, y, "text-anchor": "end" }, text);
  const figure = document.createElement("figure");
  const caption = document.createElement("figcaption");
  caption.textContent = values.some(defined) ? `${title}: tokens per value (in %)`
    : `${title} (undefined on every token: none has its log's frame 0.5 s earlier here)`;
  figure.append(caption, svg);
  return figure;
}

async function baselines(version, subset) {
  const query = new URLSearchParams({ version, subset, phase: state.submission.phase || "" });
  try {
    const board = await fetch(`${API}/leaderboard?${query}`).then((response) => (response.ok ? response.json() : { rows: [] }));
    return board.rows.filter((row) => row.baseline);
  } catch {
    return [];
  }
}

async function render() {
  const submission = state.submission;
  const results = submission.results[state.version] || {};
  const subsets = Object.keys(results);
  if (!subsets.includes(state.subset)) state.subset = subsets.includes("public") ? "public" : subsets[0];
  const scored = PAGE.versions.filter((version) => version in submission.results);
  const versionTabs = $("#version-tabs");
  versionTabs.replaceChildren(...(scored.length ? scored : PAGE.versions).map((version) =>
    tab(`${PAGE.score_labels[version]} ${version}`, version === state.version, () => { state.version = version; rendered(); })));
  for (const element of document.querySelectorAll(".score-label")) element.textContent = label("score");
  $("#subset-tabs").replaceChildren(...subsets.map((subset) =>
    tab(`${subset} tokens`, subset === state.subset, () => { state.subset = subset; rendered(); })));
  const summary = results[state.subset];
  if (!summary) {
    $("#page-error").textContent = submission.status === "scored" ? "No results on this subset." : `This submission is ${submission.status}.`;
    return;
  }
  $("#page-error").textContent = "";
  const columns = columnsOf(summary);

  // Breakdown next to the baselines (two stages: the combined score, each stage's score and subscores).
  const reference = await baselines(state.version, state.subset);
  const twoStage = "stage_one" in summary;
  $("#breakdown caption").textContent = twoStage
    ? "Each stage's summary row and the combined score (means over groups), in %, next to the baselines of the same phase"
    : BREAKDOWN_CAPTION;
  const lines = twoStage
    ? [["score", `${label("score")}, combined`, (entry) => entry.score],
      ...[["stage_one", "Stage 1: the logged frames"], ["stage_two", "Stage 2: their synthetic successors, weighted"]]
        .flatMap(([stage, title]) => [[null, title], ...["score", ...columns].map((column) =>
          [column, label(column), (entry) => (entry[stage] || {})[column]])])]
    : ["score", ...columns].map((column) => [column,
      column === "driving_direction_compliance" ? `${label(column)} (${PAGE.ddc_roles[state.version]})` : label(column),
      (entry) => entry[column]]);
  const head = $("#breakdown thead tr");
  head.replaceChildren();
  for (const text of ["Metric", submission.method, ...reference.map((row) => row.method)]) {
    const th = document.createElement("th");
    th.scope = "col";
    th.textContent = text;
    if (text !== "Metric") th.className = "num";
    head.append(th);
  }
  const body = $("#breakdown tbody");
  body.replaceChildren();
  for (const [column, text, value] of lines) {
    const row = body.insertRow();
    if (column === null) {  // a stage's rows follow under its name
      row.className = "section";
      row.append(Object.assign(document.createElement("th"), { scope: "rowgroup", colSpan: 2 + reference.length, textContent: text }));
      continue;
    }
    const name = document.createElement("th");
    name.scope = "row";
    name.textContent = text;
    name.title = PAGE.titles[column] || `${label(column)}, mean over tokens`;
    row.append(name);
    for (const entry of [summary, ...reference]) {
      const td = cell(row, "", "num");
      const meter = document.createElement("span");
      meter.className = "meter";
      const shown = value(entry);
      meter.style.setProperty("--fill", `${Math.round(100 * (shown ?? 0))}%`);
      meter.textContent = pct(shown);
      if (column === "two_frame_extended_comfort" && !defined(shown)) meter.title = `EC ${PAGE.ec_undefined}`;
      td.append(meter);
    }
  }

  await renderGroups(twoStage);

  // Histograms and the worst tokens.
  const tokens = perToken(await tokenRows(submission.id, state.version), columns);
  const figures = [histogram(label("score"), tokens.map((t) => t.values.score), 20)];
  for (const column of columns) figures.push(histogram(label(column), tokens.map((t) => t.values[column]), 10));
  $("#histograms").replaceChildren(...figures);
  const worst = $("#worst tbody");
  worst.replaceChildren();
  for (const entry of [...tokens].sort((a, b) => a.values.score - b.values.score).slice(0, WORST_SHOWN)) {
    const row = worst.insertRow();
    cell(row, sceneLink(entry.token), "token");
    cell(row, pct(entry.values.score), "num");
    const short = columns.filter((column) => defined(entry.values[column]) && entry.values[column] < 1)
      .map((column) => `${label(column)} ${pct(entry.values[column])}`);
    const filtered = entry.overridden.size ? [`human filter: ${overrides(entry)}`] : [];
    cell(row, entry.errors.length ? entry.errors.join("; ") : [...short, ...filtered].join(" · ") || "–");
  }
  renderFilter(tokens);
  await renderDiff(tokens, summary, columns);
  remember();
}

// After a change of version or subset: the page again, and the open scene redrawn under the new choice.
async function rendered() {
  await render();
  if (state.token) await showScene(state.token, { scroll: false });
}

// Two stages: per group each frame's stage-one score, its weighted stage two and the weights, lowest first.
async function renderGroups(twoStage) {
  $("#groups").hidden = !twoStage;
  if (!twoStage) return;
  const key = `${state.submission.id}/${state.version}/groups`;
  if (!(key in state.rows)) state.rows[key] = await read(`/submissions/${state.submission.id}/groups?version=${state.version}`);
  const seeds = state.rows[key].seeds;
  const choice = $("#group-seed");
  $("#group-seed-choice").hidden = seeds.length < 2;
  if (choice.options.length !== seeds.length) {
    choice.replaceChildren(...seeds.map((seed) => new Option(`${seed.seed}`, seed.seed)));
    choice.onchange = () => renderGroups(true);
  }
  const seed = seeds.find((entry) => String(entry.seed) === choice.value) || seeds[0];
  $("#group-seed-note").textContent = seeds.length > 1 ? `Seed ${seed.seed} of ${seeds.length}: ${label("score")} ${pct(seed.score)}.` : "";
  $("#group-notes").textContent = seed.official ? "" : `Where the official script would have stopped, this scores what is defined: ${seed.notes.slice(0, 5).join("; ")}${seed.note_count > 5 ? ` (and ${seed.note_count - 5} more)` : ""}.`;
  const body = $("#group-table tbody");
  body.replaceChildren();
  const order = (value) => (defined(value) ? value : Infinity);
  for (const group of [...seed.groups].sort((a, b) => order(a.score) - order(b.score))) {
    for (const [role, token, one, two] of [["now", group.original, group.original_stage_one, group.original_stage_two],
      ["0.5 s before", group.previous, group.previous_stage_one, group.previous_stage_two]]) {
      const row = body.insertRow();
      const frame = cell(row, button(token, () => showScene(token), "draw this scene"), "token");
      const small = document.createElement("small");
      small.className = "role";
      small.textContent = role;
      frame.append(small);
      if (token === group.original) {
        const value = cell(row, pct(group.score), "num score");
        value.rowSpan = 2;
        const reasons = Object.entries(group.detail).map(([what, tokens]) => `${what.replaceAll("_", " ")}: ${[].concat(tokens).join(", ")}`);
        if (reasons.length) value.append(Object.assign(document.createElement("small"), { className: "role", textContent: reasons.join("; ") }));
      }
      cell(row, pct(one), "num");
      cell(row, pct(two), "num");
      const weights = Object.entries(group.weights[token === group.original ? "original" : "previous"]);
      const list = cell(row, "", "weights");
      for (const [synthetic, weight] of weights) {
        const item = document.createElement("span");
        item.className = "weight";
        item.title = `${synthetic}: weight ${defined(weight) ? weight.toFixed(4) : "–"}`;
        item.textContent = defined(weight) ? weight.toFixed(2) : "–";
        list.append(item);
      }
    }
  }
}

// The human filter (v2.2): where the logged human scores 0 too, the column counts 1 for the agent.
function renderFilter(tokens) {
  const filtered = tokens.filter((entry) => entry.overridden.size);
  $("#human-filter").hidden = !filtered.length;
  if (!filtered.length) return;
  $("#filter-count").textContent = `${filtered.length} of ${tokens.length} tokens`;
  const body = $("#filter-tokens tbody");
  body.replaceChildren();
  for (const entry of filtered.sort((a, b) => a.values.score - b.values.score).slice(0, FILTER_SHOWN)) {
    const row = body.insertRow();
    cell(row, sceneLink(entry.token), "token");
    cell(row, pct(entry.values.score), "num");
    cell(row, overrides(entry));
  }
}

// The drill-down picture of a token under the chosen version: the wide layout (legend beside the map) on a
// desktop, the narrow one (legend under a map cropped around your path) on a phone.
async function showScene(token, { scroll = true } = {}) {
  const figure = $("#scene");
  const layout = PHONE.matches ? "narrow" : "wide";
  const query = new URLSearchParams({ version: state.version, layout });
  state.token = token;
  remember();
  $("#scene-title").textContent = `Scene drill-down: ${token}`;
  $("#scene-note").textContent = `Drawing ${token} under ${label("score")} ${state.version}…`;
  try {
    const response = await fetch(`${API}${scoped(`/submissions/${state.submission.id}/scenes/${token}.png`)}?${query}`, {
      headers: { Authorization: `Bearer ${bearer()}` },
    });
    if (!response.ok) throw new ApiError(response.status, await response.json().catch(() => ({})));
    const image = $("#scene-image");
    if (image.src) URL.revokeObjectURL(image.src);
    image.src = URL.createObjectURL(await response.blob());
    await image.decode().catch(() => {});
    image.alt = `Bird's-eye view of scene ${token} under ${label("score")} ${state.version}: the map, the objects, ` +
      "the trajectories and the first infraction of each kind, with a legend";
    $("#scene-caption").textContent = `${token} under ${label("score")} ${state.version}. Metres from the ego's start; ` +
      "every mark is in the legend; numbered boxes are the first infraction of each kind.";
    figure.hidden = false;
    $("#scene-note").textContent = "";
    if (scroll) $("#scene-title").scrollIntoView({ block: "start" });
  } catch (error) {
    figure.hidden = true;
    $("#scene-note").textContent = describeError(error);
  }
}

const KIND_LABELS = { yours: "Your submissions", published: "Published entries", baseline: "Baselines" };
const entryName = (entry) => `${entry.kind === "yours" ? `${entry.id}: ` : `${entry.team} · `}${entry.method}`;

async function otherRows(other) {
  const key = `compare/${other.id}/${state.version}`;
  if (!(key in state.rows)) {
    state.rows[key] = await read(`/submissions/${state.submission.id}/comparable/${other.id}/tokens?version=${state.version}`);
  }
  return state.rows[key];
}

// One page of a list of changed tokens, with its pager: each token a link to its drill-down here, the other
// entry's value a link to its own drill-down where it has a page (baselines have none).
function changeList(name, list, other) {
  const table = $(`#diff-${name}`);
  const tbody = table.tBodies[0];
  tbody.replaceChildren();
  const pages = Math.max(1, Math.ceil(list.length / DIFF_PAGE));
  state.pages[name] = Math.min(state.pages[name], pages - 1);
  const start = state.pages[name] * DIFF_PAGE;
  for (const change of list.slice(start, start + DIFF_PAGE)) {
    const row = tbody.insertRow();
    cell(row, sceneLink(change.token), "token");
    cell(row, pct(change.here), "num");
    cell(row, other.kind === "baseline" ? pct(change.there) : sceneLink(change.token, other.id, pct(change.there)), "num");
    cell(row, pointChange(change.here - change.there), `num ${name}`);
  }
  if (!list.length) cell(tbody.insertRow(), "none", "empty").colSpan = 4;
  const pager = $(`#diff-${name}-pages`);
  pager.hidden = pages <= 1;
  const turn = (step) => () => { state.pages[name] += step; changeList(name, list, other); };
  const previous = button("← previous", turn(-1), `tokens before ${start + 1}`);
  const next = button("next →", turn(1), `tokens after ${Math.min(start + DIFF_PAGE, list.length)}`);
  previous.disabled = state.pages[name] === 0;
  next.disabled = state.pages[name] >= pages - 1;
  const where = document.createElement("span");
  where.textContent = `${start + 1}–${Math.min(start + DIFF_PAGE, list.length)} of ${list.length}`;
  pager.replaceChildren(previous, where, next);
}

async function renderDiff(tokens, summary, columns) {
  const other = state.others.find((entry) => String(entry.id) === state.compare);
  $("#diff").hidden = !other;
  if (!other) return;
  $("#other").value = state.compare;
  const otherSummary = (other.results[state.version] || {})[state.subset];
  $("#diff-other-name").textContent = entryName(other);
  const means = $("#diff-means tbody");
  means.replaceChildren();
  for (const column of ["score", ...columns]) {
    const row = means.insertRow();
    cell(row, label(column));
    const here = summary[column], there = otherSummary ? otherSummary[column] : null;
    cell(row, pct(here), "num");
    cell(row, pct(there), "num");
    const shown = pointChange(defined(here) && defined(there) ? here - there : null);
    // Colour only a change that shows in the rounded figure.
    cell(row, shown, shown.startsWith("+") ? "num better" : shown.startsWith("-") ? "num worse" : "num");
  }
  const theirs = new Map(perToken(await otherRows(other), columns).map((entry) => [entry.token, entry]));
  const changes = tokens.filter((entry) => theirs.has(entry.token))
    .map((entry) => ({ token: entry.token, here: entry.values.score, there: theirs.get(entry.token).values.score }));
  const better = changes.filter((c) => c.here > c.there).sort((a, b) => (b.here - b.there) - (a.here - a.there));
  const worse = changes.filter((c) => c.here < c.there).sort((a, b) => (a.here - a.there) - (b.here - b.there));
  $("#diff-counts").textContent = `Per token: ${better.length} better, ${worse.length} worse, ` +
    `${changes.length - better.length - worse.length} the same (of ${counted(changes.length, "token")} both scored). ` +
    "Every differing token is listed, the largest change first; open one to draw its scene.";
  changeList("better", better, other);
  changeList("worse", worse, other);
}

async function load() {
  try {
    state.submission = await read(`/submissions/${PAGE.submission_id}`);
  } catch (error) {
    if (error instanceof ApiError && error.status === 401) sessionStorage.removeItem(TOKEN_KEY);
    $("#title").textContent = `Submission ${PAGE.submission_id}`;
    $("#signin").hidden = false;
    $("#signin-error").textContent = describeError(error);
    return;
  }
  const submission = state.submission;
  $("#signin").hidden = true;
  $("#submission").hidden = false;
  $("#title").textContent = `${submission.method} (submission ${submission.id})`;
  $("#facts").textContent = `${submission.team} · phase ${submission.phase ?? "–"} · split ${submission.split} · ` +
    `${submission.status} · ${counted(submission.seed_count, "seed")}, ${counted(submission.token_count, "token")} · submitted ${when(submission.submitted_at)} UTC`;
  const sanctions = [
    submission.disqualified && `Disqualified by an organiser${submission.disqualified_reason ? `: ${submission.disqualified_reason}` : ""}.`,
    submission.admin_hidden && "Hidden from the leaderboard by an organiser.",
    submission.hidden && "Hidden from the leaderboard by its team.",
  ].filter(Boolean);
  $("#sanctions").textContent = sanctions.join(" ");
  $("#sanctions").hidden = !sanctions.length;
  state.others = await read(`/submissions/${submission.id}/comparable`).catch(() => []);
  $("#compare").hidden = !state.others.length;
  const select = $("#other");
  const groups = Object.entries(KIND_LABELS).map(([kind, text]) => {
    const group = document.createElement("optgroup");
    group.label = text;
    group.append(...state.others.filter((entry) => entry.kind === kind).map((entry) => new Option(entryName(entry), entry.id)));
    return group;
  }).filter((group) => group.children.length);
  select.replaceChildren(new Option("choose…", ""), ...groups);
  select.value = state.others.some((entry) => String(entry.id) === state.compare) ? state.compare : "";
  state.compare = select.value;
  select.addEventListener("change", () => { state.compare = select.value; state.pages = { better: 0, worse: 0 }; render(); });
  if (!(state.version in submission.results)) state.version = Object.keys(submission.results)[0] || state.version;
  await render();
  if (state.token) await showScene(state.token);
}

$("#signin").addEventListener("submit", async (event) => {
  event.preventDefault();
  sessionStorage.setItem(TOKEN_KEY, $("#token").value.trim());
  $("#signin-error").textContent = "";
  await load();
});

load();
