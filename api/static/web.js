// Live status: every 2 s, re-fetch each [data-live] block that still holds a queued or running item
// ([data-active] inside it) and swap its HTML. Nothing else on the page uses JavaScript.
setInterval(async () => {
  for (const el of document.querySelectorAll("[data-live]")) {
    if (!el.querySelector("[data-active]")) continue;
    try {
      const r = await fetch(el.dataset.live, {credentials: "same-origin"});
      if (r.ok) el.innerHTML = await r.text();
    } catch (e) { /* the server is restarting: try again next tick */ }
  }
}, 2000);
