// One way to say when something happened, on every page: the browser's local time,
// 24-hour, to the second ("14:05:09"). Server-rendered times are
// <time datetime="ISO" data-clock> elements, rewritten here to the same form.
(() => {
  "use strict";
  const FORMAT = { hour: "2-digit", minute: "2-digit", second: "2-digit", hourCycle: "h23" };

  function clock(when) {
    const at = when instanceof Date ? when : new Date(when);
    return Number.isNaN(at.getTime()) ? "" : at.toLocaleTimeString([], FORMAT);
  }

  window.IoUV = Object.assign(window.IoUV || {}, { clock });
  document.addEventListener("DOMContentLoaded", () => {
    for (const node of document.querySelectorAll("time[datetime][data-clock]")) {
      node.textContent = clock(node.getAttribute("datetime"));
    }
  });
})();
