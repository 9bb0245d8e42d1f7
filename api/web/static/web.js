// Live status: every 2 s, re-fetch each [data-live] block that still holds a queued or running item
// ([data-active] inside it) and swap its HTML. Besides, the column menu's arrows (below).
// A block the user is working in (a run ticked, a list open, a field focused) is left alone: a swap would lose it.
setInterval(async () => {
  for (const el of document.querySelectorAll("[data-live]")) {
    if (!el.querySelector("[data-active]")) continue;
    if (el.querySelector("input[name=sel]:checked, details[open]") || el.contains(document.activeElement)) continue;
    try {
      const r = await fetch(el.dataset.live, {credentials: "same-origin"});
      if (r.ok) {
        el.innerHTML = await r.text();
        addMoves(el);
      }
    } catch (e) { /* the server is restarting: try again next tick */ }
  }
}, 2000);

// The column menu (runs table): an up and a down arrow beside each column move it in its list; the form sends
// the ticked columns in the list's order, which the URL keeps. Without JavaScript the menu still ticks columns.
function addMoves(root) {
  for (const li of root.querySelectorAll("ol.colorder li")) {
    const box = li.querySelector("input[type=checkbox]");
    if (!box || li.querySelector("button.move")) continue;
    const name = li.textContent.trim();
    for (const [dir, text] of [["up", "↑"], ["down", "↓"]]) {
      const b = document.createElement("button");
      b.type = "button";
      b.className = "move";
      b.textContent = text;
      b.dataset.dir = dir;
      b.setAttribute("aria-label", `move ${name} ${dir}`);
      li.append(b);
    }
  }
}

document.addEventListener("click", (e) => {
  const b = e.target.closest && e.target.closest("button.move");
  if (!b) return;
  const li = b.closest("li");
  if (b.dataset.dir === "up" && li.previousElementSibling) li.previousElementSibling.before(li);
  if (b.dataset.dir === "down" && li.nextElementSibling) li.nextElementSibling.after(li);
  li.querySelector("input").checked = true;
  b.focus();
});

addMoves(document);
