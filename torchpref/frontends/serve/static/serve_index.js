"use strict";
// The landing page: start a new session and go to its link (Enter on the focused button).
document.getElementById("start").focus();
document.getElementById("start").addEventListener("click", async (ev) => {
  ev.target.disabled = true;
  const msg = document.getElementById("message");
  // a recruitment platform's id for the participant, from this page's link (?participant=ID)
  const participant = new URLSearchParams(window.location.search).get("participant");
  try {
    const r = await fetch("api/new", { method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(participant ? { participant } : {}) });
    const data = await r.json();
    if (!r.ok) throw new Error(data.error || r.statusText);
    window.location.href = data.url;
  } catch (e) {
    msg.textContent = "Could not start a session: " + e.message;
    ev.target.disabled = false;
  }
});
