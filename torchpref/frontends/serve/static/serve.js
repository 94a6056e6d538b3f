"use strict";
// torchpref serve: one question at a time. The page asks the server for the session's current
// question (state), shows it, and posts the answer with the seconds since it was first shown.
// An answer is acknowledged by the server only once it is in the session file; until then the
// page retries (a restarted server answers the retry, or says it already has the answer).
(() => {
  const LETTERS = "ABCDEFGHIJKLMNOPQRSTUVWXYZ";
  const RETRY_MS = 400;
  const RETRY_FOR_MS = 180000;
  const $ = (id) => document.getElementById(id);
  let state = null;
  let busy = false;
  let ready = false; // the question on screen is shown in full (its pictures decoded)
  // what tests and studies can read: every acknowledged answer, and the server's time for each
  const log = { acked: [], serverMs: [], refused: [] };
  window.torchpref = { log, state: () => state };

  function el(tag, attrs, ...children) {
    const node = document.createElement(tag);
    for (const [k, v] of Object.entries(attrs || {})) {
      if (k === "dataset") Object.assign(node.dataset, v);
      else if (v !== null && v !== undefined) node.setAttribute(k, v);
    }
    for (const c of children) node.append(c); // strings become text nodes: never HTML
    return node;
  }

  function message(text, ok) {
    $("message").textContent = text || "";
    $("message").className = ok ? "ok" : "";
  }

  // A question's clock starts when everything it shows is on screen (its pictures decoded), not
  // when its state arrives: until then the answer controls are disabled ("loading"). The time it
  // was shown is kept in the tab's sessionStorage, so a reload does not restart the clock.
  const shownKey = (qid) => "torchpref-shown:" + location.pathname + ":" + qid;
  const shownTimes = {};
  function markShown(qid) {
    let t = null;
    try {
      t = Number(sessionStorage.getItem(shownKey(qid))) || null;
      if (!t) sessionStorage.setItem(shownKey(qid), String(Date.now()));
    } catch (e) { /* storage off: timed from this showing */ }
    if (!shownTimes[qid]) shownTimes[qid] = t || Date.now();
  }
  function shownAt(qid) {
    let t = null;
    try { t = Number(sessionStorage.getItem(shownKey(qid))) || null; } catch (e) { t = null; }
    return t || shownTimes[qid] || null;
  }

  function card(o, title, button) {
    const rows = o.features.map(([n, v]) => el("tr", {}, el("td", {}, n), el("td", {}, v)));
    const head = el("div", { class: "card-head" }, el("h3", {}, title));
    if (button) head.append(button); // the answer beside the title: the card's height is its picture's
    const c = el("div", { class: "option" }, head);
    if (o.picture) {
      const img = el("img", { src: o.picture, alt: "picture of " + o.label, class: "picture" });
      const zoom = el("button", { type: "button", class: "enlarge", title: "Enlarge (click, or Shift + its letter)",
                                  "aria-label": "Enlarge " + title }, img);
      zoom.addEventListener("click", () => enlarge(o.picture, title));
      c.append(zoom);
    }
    c.append(el("table", { class: "features" }, el("tbody", {}, ...rows)));
    return c;
  }

  function enlarge(src, title) {
    const dialog = $("zoom");
    $("zoom-title").textContent = title;
    $("zoom-img").src = src;
    $("zoom-img").alt = "enlarged picture of " + title;
    if (!dialog.open) dialog.showModal();
    $("zoom-close").focus();
  }

  function answerButton(text, answer, key) {
    const b = el("button", { class: "answer", type: "button", title: "key " + key, disabled: "" }, text);
    b.addEventListener("click", () => submit(answer));
    return b;
  }

  function renderRating(q, s, box) {
    const o = q.options[0];
    const k = q.levels;
    if (k) {
      box.append(el("h1", {}, `Rate this ${s.noun} from 1 (${q.words["1"]}) to ${k} (${q.words[String(k)]})`));
      const levels = el("div", { class: "levels", role: "group", "aria-label": "rating" });
      for (let j = 1; j <= k; j++) {
        const word = q.words[String(j)] ? " " + q.words[String(j)] : "";
        levels.append(answerButton(String(j) + word, j, j <= 9 ? String(j) : "-"));
      }
      const c = card(o, o.label);
      c.classList.add("single");
      box.append(c, levels);
    } else {
      box.append(el("h1", {}, `Rate this ${s.noun} from 0 (worst) to 1 (best)`));
      const slider = el("input", { type: "range", min: "0", max: "1", step: "0.01", value: "0.5", id: "slider",
                                   "aria-label": "rating from 0 to 1", disabled: "" });
      const go = el("button", { class: "answer", type: "button", disabled: "" }, "Submit rating (Enter)");
      go.addEventListener("click", () => submit(Number(slider.value)));
      slider.addEventListener("keydown", (ev) => { if (ev.key === "Enter") submit(Number(slider.value)); });
      box.append(card(o, o.label), el("div", { class: "levels" }, slider, go));
    }
  }

  function renderRanking(q, s, box) {
    box.append(el("h1", {}, `Which ${s.noun} is best?`));
    const opts = el("div", { class: "options", "data-m": String(q.options.length) });
    q.options.forEach((o, i) => {
      const L = LETTERS[i];
      opts.append(card(o, `${L}: ${o.label}`, answerButton(`${L} is best`, i, `${L} or ${i + 1}`)));
    });
    box.append(opts);
    // "no preference" sits in the row of undo and the messages, below the options and in view
    if (q.ties) $("ties-slot").append(answerButton("No preference (0)", null, "0 or ="));
  }

  function render(s) {
    state = s;
    busy = false;
    ready = false;
    const box = $("question");
    box.replaceChildren();
    $("ties-slot").replaceChildren();
    $("progress").max = s.total;
    $("progress").value = Math.min(s.answered, s.total);
    $("undo").disabled = !s.can_undo;
    if (s.done) {
      $("progress-text").textContent = `All ${s.total} questions answered.`;
      const link = el("a", { href: "summary", id: "to-summary" }, "See what was learned (Enter)");
      box.append(el("h1", {}, "Thank you!"));
      const done = s.completion || {};
      if (done.code) box.append(el("p", { id: "completion-code" }, `Your completion code: ${done.code}`));
      if (done.redirect) {
        const go = el("a", { href: done.redirect, id: "completion-redirect", rel: "noreferrer" }, "Continue (Enter)");
        box.append(el("p", {}, go));
        go.focus();
      } else {
        box.append(el("p", {}, link));
        link.focus();
      }
    } else {
      $("progress-text").textContent = `Question ${s.answered + 1} of ${s.total}`;
      if (s.question.kind === "rating") renderRating(s.question, s, box);
      else renderRanking(s.question, s, box);
      showWhenDecoded(s.qid, box);
    }
    const rec = $("recommended");
    rec.hidden = !s.recommended;
    if (s.recommended) $("recommended-label").textContent = s.recommended.label;
    $("recommended-body").replaceChildren(...(s.recommended ? [card(s.recommended, s.recommended.label)] : []));
    document.body.dataset.qid = s.qid;
    document.body.dataset.answered = String(s.answered);
  }

  // The answer controls wait for the question's pictures: the clock starts once they are decoded.
  async function showWhenDecoded(qid, box) {
    box.classList.add("loading");
    box.setAttribute("aria-busy", "true");
    document.body.dataset.ready = "false";
    const imgs = [...box.querySelectorAll("img")];
    const failed = (await Promise.all(imgs.map((i) => i.decode().then(() => false, () => true)))).some((x) => x);
    if (!state || state.qid !== qid || box !== $("question")) return; // another question since
    box.classList.remove("loading");
    box.setAttribute("aria-busy", "false");
    if (failed) message("A picture could not be shown; answer from the figures, or reload the page.");
    markShown(qid);
    ready = true;
    document.body.dataset.ready = "true";
    setEnabled(true);
    const first = box.querySelector("button.answer, input");
    if (first) first.focus();
  }

  function setEnabled(on) {
    for (const b of document.querySelectorAll("#question button, #question input, #ties-slot button, #undo")) {
      b.disabled = !on;
    }
    if (on && state) $("undo").disabled = !state.can_undo;
  }

  const sleep = (ms) => new Promise((r) => setTimeout(r, ms));

  async function post(path, body) {
    const start = Date.now();
    for (;;) {
      try {
        const r = await fetch(path, { method: "POST", headers: { "Content-Type": "application/json" },
                                      body: JSON.stringify(body), cache: "no-store" });
        if (r.status >= 500) { // not saved (a full disk, a restart): said, then tried again
          let why = "server error " + r.status;
          try { why = (await r.json()).error || why; } catch (e) { /* not JSON */ }
          throw new Error(why);
        }
        const timing = r.headers.get("Server-Timing");
        const data = await r.json();
        return { status: r.status, data, timing };
      } catch (e) {
        if (Date.now() - start > RETRY_FOR_MS) return { status: 0, data: { error: "the server cannot be reached" } };
        message(e.message && !/fetch|network/i.test(e.message) ? e.message + " Trying again…"
          : "The connection was lost; trying again… (nothing you answered is lost)");
        await sleep(RETRY_MS);
      }
    }
  }

  async function submit(answer) {
    if (busy || !ready || !state || state.done) return;
    busy = true;
    setEnabled(false);
    const qid = state.qid;
    const shown = shownAt(qid);
    const answered = Math.max(Date.now(), shown || 0);
    const body = { qid, answer, response_time: shown ? (answered - shown) / 1000 : null };
    if (shown) Object.assign(body, { shown_at: shown, answered_at: answered });
    const r = await post("answer", body);
    if (r.status === 200) {
      log.acked.push({ qid, answer, response_time: body.response_time, shown_at: body.shown_at,
                       duplicate: !!r.data.duplicate });
      const m = /dur=([0-9.]+)/.exec(r.timing || "");
      if (m) log.serverMs.push(Number(m[1]));
      try { sessionStorage.removeItem(shownKey(qid)); } catch (e) { /* nothing kept */ }
      message(answer === null ? "Saved: no preference." : "Saved.", true);
      render(r.data);
      return;
    }
    log.refused.push({ qid, answer, status: r.status, error: r.data.error });
    message(r.data.error || "That answer was not recorded.");
    if (r.data.state) render(r.data.state);
    else { busy = false; setEnabled(true); }
  }

  async function undo() {
    if (busy || !state || !state.can_undo) return;
    busy = true;
    setEnabled(false);
    const r = await post("undo", { qid: state.qid });
    if (r.status === 200) message("Your last answer was withdrawn; it is asked again.", true);
    else message(r.data.error || "Nothing was undone.");
    if (r.data.state || r.status === 200) render(r.status === 200 ? r.data : r.data.state);
    else { busy = false; setEnabled(true); }
  }

  function onKey(ev) {
    if (ev.ctrlKey || ev.metaKey || ev.altKey || !state) return;
    if (ev.target && ev.target.tagName === "INPUT") return;
    if ($("zoom").open) return; // the enlarged picture: Escape closes it first
    const key = ev.key;
    if (state.done) { if (key === "u" || key === "U") { ev.preventDefault(); undo(); } return; }
    const q = state.question;
    if (ev.shiftKey && /^[A-Z]$/.test(key) && q.kind === "ranking") { // Shift + a letter: enlarge that option
      const o = q.options[LETTERS.indexOf(key)];
      if (o && o.picture) { ev.preventDefault(); enlarge(o.picture, `${key}: ${o.label}`); }
      return;
    }
    if (key === "u" || key === "U") { ev.preventDefault(); undo(); return; }
    if (!ready) return; // nothing is answered before it is on screen
    let answer;
    if (q.kind === "rating") {
      if (!q.levels || !/^[1-9]$/.test(key) || Number(key) > q.levels) return;
      answer = Number(key);
    } else if ((key === "0" || key === "=") && q.ties) {
      answer = null;
    } else if (/^[1-9]$/.test(key) && Number(key) <= q.options.length) {
      answer = Number(key) - 1;
    } else if (/^[a-zA-Z]$/.test(key) && LETTERS.indexOf(key.toUpperCase()) < q.options.length) {
      answer = LETTERS.indexOf(key.toUpperCase());
    } else return;
    ev.preventDefault();
    submit(answer);
  }

  async function load() {
    for (let attempt = 0; attempt < 450; attempt++) {
      try {
        const r = await fetch("state", { cache: "no-store" });
        if (r.status === 503) throw new Error("busy");  // out of memory or files for a moment: try again
        const data = await r.json();
        if (!r.ok) { message(data.error || "This session cannot be shown."); return; }
        render(data);
        return;
      } catch (e) {
        message("Waiting for the server…");
        await sleep(RETRY_MS);
      }
    }
  }

  document.addEventListener("keydown", onKey);
  $("zoom-close").addEventListener("click", () => $("zoom").close());
  $("zoom").addEventListener("click", (ev) => { if (ev.target === $("zoom")) $("zoom").close(); });
  $("undo").addEventListener("click", undo);
  load();
})();
