// Submission page: the per-metric breakdown next to the phase's baselines, histograms of per-token PDMS
// and of each subscore, the tokens that lost most, and a per-token diff with another of the team's
// submissions. Everything comes from the team API (common.js); histograms are drawn as inline SVG.
"use strict";

const PAGE = JSON.parse($("#page-data").textContent);
const LABELS = PAGE.labels; // devkit column -> short name
const WORST_SHOWN = 15;
const DIFF_SHOWN = 10;
// The owning team reads it with its token; an organiser who opened the admin console, with the admin's;
// anyone else, once the entry is published (its phase has closed), through the public routes.
const ADMIN_TOKEN_KEY = "navsim-lb-admin-token";
const mode = () => (token() ? "team" : sessionStorage.getItem(ADMIN_TOKEN_KEY) ? "admin" : "public");
const bearer = () => (mode() === "admin" ? sessionStorage.getItem(ADMIN_TOKEN_KEY) : token());
const scoped = (path) => ({ team: path, admin: `/admin${path}`, public: path.replace("/submissions/", "/published/") })[mode()];
const read = (path) => api("GET", scoped(path), { bearer: bearer() });
const state = { submission: null, version: PAGE.default_version, subset: null, rows: {}, others: [] };

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

function histogram(title, values, bins) {
  const width = 260, height = 120, pad = 18;
  const counts = new Array(bins).fill(0);
  for (const value of values.filter(defined)) counts[Math.min(bins - 1, Math.max(0, Math.floor(value * bins)))] += 1;
  const top = Math.max(1, ...counts);
  const bar = (width - 2 * pad) / bins;
  const svg = document.createElementNS("http://www.w3.org/2000/svg", "svg");
  svg.setAttribute("viewBox", `0 0 ${width} ${height + 16}`);
  svg.setAttribute("role", "img");
  svg.setAttribute("aria-label", `${title}: ${counts.map((count, i) => `${count} tokens in ${(i / bins).toFixed(2)}–${((i + 1) / bins).toFixed(2)}`).join(", ")}`);
  counts.forEach((count, index) => {
    const rect = document.createElementNS(svg.namespaceURI, "rect");
    const h = (count / top) * (height - pad);
    rect.setAttribute("x", pad + index * bar + 0.5);
    rect.setAttribute("y", height - h);
    rect.setAttribute("width", Math.max(1, bar - 1));
    rect.setAttribute("height", h);
    rect.setAttribute("class", index === bins - 1 ? "bar full" : "bar");
    const tip = document.createElementNS(svg.namespaceURI, "title");
    tip.textContent = `${count} token(s) with ${(index / bins).toFixed(2)} ≤ value ${index === bins - 1 ? "≤" : "<"} ${((index + 1) / bins).toFixed(2)}`;
    rect.append(tip);
    svg.append(rect);
  });
  for (const [x, text] of [[pad, "0"], [width / 2, "0.5"], [width - pad, "1"]]) {
    const tick = document.createElementNS(svg.namespaceURI, "text");
    tick.setAttribute("x", x);
    tick.setAttribute("y", height + 13);
    tick.setAttribute("text-anchor", "middle");
    tick.textContent = text;
    svg.append(tick);
  }
  const figure = document.createElement("figure");
  const caption = document.createElement("figcaption");
  caption.textContent = values.some(defined) ? `${title} (max bar: ${top} tokens)`
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
    tab(`${PAGE.score_labels[version]} ${version}`, version === state.version, () => { state.version = version; render(); })));
  for (const element of document.querySelectorAll(".score-label")) element.textContent = label("score");
  $("#subset-tabs").replaceChildren(...subsets.map((subset) =>
    tab(`${subset} tokens`, subset === state.subset, () => { state.subset = subset; render(); })));
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
    ? [["score", `${label("score")} (combined)`, (entry) => entry.score],
      ...["stage_one", "stage_two"].flatMap((stage, index) => ["score", ...columns].map((column) =>
        [column, `${column === "score" ? label("score") : label(column)}, stage ${index + 1}`, (entry) => (entry[stage] || {})[column]]))]
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
    const name = document.createElement("th");
    name.scope = "row";
    name.textContent = text;
    name.title = column;
    row.append(name);
    for (const entry of [summary, ...reference]) {
      const td = cell(row, "", "num");
      const meter = document.createElement("span");
      meter.className = "meter";
      meter.style.setProperty("--fill", `${Math.round(100 * (value(entry) ?? 0))}%`);
      meter.textContent = pct(value(entry));
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
    cell(row, button(entry.token, () => showScene(entry.token), "draw this scene"), "token");
    cell(row, pct(entry.values.score), "num");
    const short = columns.filter((column) => defined(entry.values[column]) && entry.values[column] < 1)
      .map((column) => `${label(column)} ${pct(entry.values[column])}`);
    const filtered = entry.overridden.size ? [`human filter: ${overrides(entry)}`] : [];
    cell(row, entry.errors.length ? entry.errors.join("; ") : [...short, ...filtered].join(" · ") || "–");
  }
  renderFilter(tokens);
  await renderDiff(tokens, summary, columns);
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
    cell(row, button(entry.token, () => showScene(entry.token), "draw this scene"), "token");
    cell(row, pct(entry.values.score), "num");
    cell(row, overrides(entry));
  }
}

async function showScene(token) {
  const figure = $("#scene");
  const query = new URLSearchParams({ version: state.version });
  $("#scene-note").textContent = `Drawing ${token}…`;
  try {
    const response = await fetch(`${API}${scoped(`/submissions/${state.submission.id}/scenes/${token}.png`)}?${query}`, {
      headers: { Authorization: `Bearer ${bearer()}` },
    });
    if (!response.ok) throw new ApiError(response.status, await response.json().catch(() => ({})));
    const image = $("#scene-image");
    if (image.src) URL.revokeObjectURL(image.src);
    image.src = URL.createObjectURL(await response.blob());
    image.alt = `Bird's-eye view of scene ${token} under ${label("score")} ${state.version}`;
    $("#scene-caption").textContent = `${token}, ${label("score")} ${state.version}: metres from the ego's start; objects white now, grey every second ahead; red: the first infraction of each kind and the object involved.`;
    figure.hidden = false;
    $("#scene-note").textContent = "";
    figure.scrollIntoView({ behavior: "smooth", block: "start" });
  } catch (error) {
    figure.hidden = true;
    $("#scene-note").textContent = describeError(error);
  }
}

async function renderDiff(tokens, summary, columns) {
  const otherId = $("#other").value;
  $("#diff").hidden = !otherId;
  if (!otherId) return;
  const other = state.others.find((submission) => String(submission.id) === otherId);
  const otherSummary = (other.results[state.version] || {})[state.subset];
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
  const theirs = new Map(perToken(await tokenRows(other.id, state.version), columns).map((entry) => [entry.token, entry]));
  const changes = tokens.filter((entry) => theirs.has(entry.token))
    .map((entry) => ({ token: entry.token, here: entry.values.score, there: theirs.get(entry.token).values.score }));
  const better = changes.filter((c) => c.here > c.there).sort((a, b) => (b.here - b.there) - (a.here - a.there));
  const worse = changes.filter((c) => c.here < c.there).sort((a, b) => (a.here - a.there) - (b.here - b.there));
  $("#diff-counts").textContent = `Per token: ${better.length} better, ${worse.length} worse, ${changes.length - better.length - worse.length} the same (of ${changes.length} tokens both scored).`;
  for (const [table, list] of [["#diff-better", better], ["#diff-worse", worse]]) {
    const tbody = $(`${table} tbody`);
    tbody.replaceChildren();
    for (const change of list.slice(0, DIFF_SHOWN)) {
      const row = tbody.insertRow();
      cell(row, change.token, "token");
      cell(row, pct(change.here), "num");
      cell(row, pct(change.there), "num");
    }
    if (!list.length) cell(tbody.insertRow(), "none", "empty").colSpan = 3;
  }
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
    `${submission.status} · ${submission.seed_count} seed(s), ${submission.token_count} tokens · submitted ${when(submission.submitted_at)} UTC`;
  const sanctions = [
    submission.disqualified && `Disqualified by an organiser${submission.disqualified_reason ? `: ${submission.disqualified_reason}` : ""}.`,
    submission.admin_hidden && "Hidden from the leaderboard by an organiser.",
    submission.hidden && "Hidden from the leaderboard by its team.",
  ].filter(Boolean);
  $("#sanctions").textContent = sanctions.join(" ");
  $("#sanctions").hidden = !sanctions.length;
  const mine = { team: "/submissions", admin: `/submissions?team_id=${submission.team_id}` }[mode()];
  // Only entries of the same split compare token by token.
  state.others = mine ? (await read(mine)).filter((s) => s.id !== submission.id && s.status === "scored" && s.split === submission.split) : [];
  $("#compare").hidden = !state.others.length;
  const select = $("#other");
  select.replaceChildren(new Option("choose…", ""), ...state.others.map((s) => new Option(`${s.id}: ${s.method}`, s.id)));
  select.addEventListener("change", () => render());
  if (!(state.version in submission.results)) state.version = Object.keys(submission.results)[0] || state.version;
  await render();
}

$("#signin").addEventListener("submit", async (event) => {
  event.preventDefault();
  sessionStorage.setItem(TOKEN_KEY, $("#token").value.trim());
  $("#signin-error").textContent = "";
  await load();
});

load();
