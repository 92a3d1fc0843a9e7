// Board rows that have a page (a published entry's) open it when clicked anywhere, not only on the method's
// name; a click on a link or a button inside the row keeps its own meaning. The name stays the row's link for
// the keyboard and for opening in a new tab.
(function () {
  "use strict";
  document.addEventListener("click", (event) => {
    const row = event.target.closest("tr[data-href]");
    if (!row || event.target.closest("a, button, abbr") || window.getSelection().toString()) return;
    if (event.ctrlKey || event.metaKey) window.open(row.dataset.href, "_blank", "noopener");
    else location.assign(row.dataset.href);
  });
})();
