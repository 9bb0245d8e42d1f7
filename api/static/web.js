// Live status: every 2 s, re-fetch each [data-live] block that still holds a queued or running item
// ([data-active] inside it) and swap its HTML. Nothing else on the page uses JavaScript.
// A block the user is working in (a run ticked, a list open, a field focused) is left alone: a swap would lose it.
setInterval(async () => {
  for (const el of document.querySelectorAll("[data-live]")) {
    if (!el.querySelector("[data-active]")) continue;
    if (el.querySelector("input[name=sel]:checked, details[open]") || el.contains(document.activeElement)) continue;
    try {
      const r = await fetch(el.dataset.live, {credentials: "same-origin"});
      if (r.ok) el.innerHTML = await r.text();
    } catch (e) { /* the server is restarting: try again next tick */ }
  }
}, 2000);
