// Sortable tables: a header button sorts the rows by that column, a second click reverses the order.
// Cells carry their sort value in data-value; the active header carries aria-sort; ?sort=key&order=asc|desc
// in the address keeps the order on reload and in shared links.
(function () {
  "use strict";

  function compare(type, a, b) {
    if (type === "number") return parseFloat(a) - parseFloat(b);
    return a.localeCompare(b);
  }

  function sortTable(table, header, order) {
    const index = Array.prototype.indexOf.call(header.parentNode.children, header);
    const type = header.dataset.type;
    const body = table.tBodies[0];
    const rows = Array.from(body.rows).filter((row) => row.cells.length > index && row.cells[index].dataset.value !== undefined);
    const sign = order === "ascending" ? 1 : -1;
    // Stable sort: equal values keep the PDMS order they arrived in.
    rows
      .map((row, position) => ({ row, position }))
      .sort((a, b) => sign * compare(type, a.row.cells[index].dataset.value, b.row.cells[index].dataset.value) || a.position - b.position)
      .forEach(({ row }) => body.appendChild(row));
    table.querySelectorAll("th[aria-sort]").forEach((th) => th.removeAttribute("aria-sort"));
    header.setAttribute("aria-sort", order);
  }

  function defaultOrder(header) {
    // Ranks and text read best ascending; scores read best descending.
    return header.dataset.key === "rank" || header.dataset.type === "text" ? "ascending" : "descending";
  }

  document.querySelectorAll("table[data-sortable]").forEach((table) => {
    table.querySelectorAll("th[data-key]").forEach((header) => {
      header.querySelector("button").addEventListener("click", () => {
        const current = header.getAttribute("aria-sort");
        const order = current ? (current === "ascending" ? "descending" : "ascending") : defaultOrder(header);
        sortTable(table, header, order);
        const url = new URL(window.location.href);
        url.searchParams.set("sort", header.dataset.key);
        url.searchParams.set("order", order === "ascending" ? "asc" : "desc");
        history.replaceState(null, "", url);
      });
    });
    const params = new URLSearchParams(window.location.search);
    const initial = params.get("sort") && table.querySelector(`th[data-key="${CSS.escape(params.get("sort"))}"]`);
    if (initial) sortTable(table, initial, params.get("order") === "asc" ? "ascending" : "descending");
  });
})();
