// Actions with consequences ask once and say what the vehicle will do.
//
// A form with data-confirm="End the session?" asks that question, followed by its
// data-consequence ("quad-1 will fly back to its home point and land."), before it is
// sent; "Cancel" sends nothing. Pages keep data-consequence current as vehicles change
// (controller.js does, from the session feed).
(() => {
  "use strict";
  document.addEventListener("submit", (event) => {
    const form = event.target;
    if (!(form instanceof HTMLFormElement) || !form.dataset.confirm) return;
    const question = [form.dataset.confirm, form.dataset.consequence].filter(Boolean).join(" ");
    if (!window.confirm(question)) event.preventDefault();
  }, true);
})();
