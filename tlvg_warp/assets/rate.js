"use strict";
// The user study page: fetches the rater's next item, shows it, posts the three choices, and repeats.
const rater = document.body.dataset.rater;
const $ = (sel) => document.querySelector(sel);
let current = null;
window.rateState = () => current;  // read by the tests and handy in the console

async function api(path, body) {
  const url = path + "?rater=" + encodeURIComponent(rater);
  const opts = body === undefined ? {} : {method: "POST", headers: {"Content-Type": "application/json"},
                                           body: JSON.stringify(body)};
  const r = await fetch(url, opts);
  const j = await r.json();
  if (!r.ok && !j.next) throw new Error(j.error || ("HTTP " + r.status));
  return j;
}

function buildCriteria(criteria) {
  const box = $("#criteria");
  if (box.childElementCount) return;
  for (const c of criteria) {
    const name = document.createElement("div");
    name.innerHTML = '<span class="crit-name"></span><span class="crit-q"></span>';
    name.querySelector(".crit-name").textContent = c.name;
    name.querySelector(".crit-q").textContent = c.question;
    const choices = document.createElement("div");
    choices.className = "choices";
    for (const side of ["left", "right"]) {
      const label = document.createElement("label");
      const input = document.createElement("input");
      input.type = "radio"; input.name = c.key; input.value = side; input.required = true;
      input.addEventListener("change", update);
      label.append(input, side === "left" ? "Left" : "Right");
      choices.append(label);
    }
    box.append(name, choices);
  }
}

function update() {
  const all = current && !current.done &&
      current.criteria.every((c) => document.querySelector(`input[name="${c.key}"]:checked`));
  $("#submit").disabled = !all;
}

function mediaElement(kind, src, onload) {
  const el = document.createElement(kind === "video" ? "video" : "img");
  if (kind === "video") {
    Object.assign(el, {autoplay: true, loop: true, muted: true, playsInline: true, controls: true});
    el.addEventListener("loadeddata", onload, {once: true});
  } else {
    el.alt = "";
    el.addEventListener("load", onload, {once: true});
  }
  el.src = src;
  return el;
}

function show(n) {
  current = n;
  document.body.dataset.loaded = "";
  const done = n.answered + (n.done ? 0 : 1);
  $("#progress").textContent = n.done ? `${n.answered} of ${n.total} rated` : `item ${done} of ${n.total}`;
  for (const input of document.querySelectorAll('input[name="expertise"]')) input.checked = input.value === n.expertise;
  $("#study").hidden = n.done;
  $("#done").hidden = !n.done;
  if (n.done) return;
  buildCriteria(n.criteria);
  for (const input of document.querySelectorAll("#criteria input")) input.checked = false;
  let pending = 3;
  const loaded = () => { if (--pending === 0) document.body.dataset.loaded = n.item; };
  const painting = $("#painting");
  painting.onload = loaded;
  painting.src = n.painting;
  $("#left").replaceChildren(mediaElement(n.kind, n.left, loaded));
  $("#right").replaceChildren(mediaElement(n.kind, n.right, loaded));
  $("#status").textContent = "";
  update();
  window.scrollTo(0, 0);
}

$("#answer").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  if (!current || current.done) return;
  const choice = {};
  for (const c of current.criteria) choice[c.key] = document.querySelector(`input[name="${c.key}"]:checked`).value;
  $("#submit").disabled = true;
  $("#status").textContent = "saving ...";
  try {
    const r = await api("/api/answer", {item: current.item, position: current.position, choice});
    show(r.next);
  } catch (e) {
    $("#status").textContent = "not saved: " + e.message + " (try again)";
    update();
  }
});

for (const input of document.querySelectorAll('input[name="expertise"]')) {
  input.addEventListener("change", async () => {
    try {
      await api("/api/expertise", {expertise: input.value});
      $("#expertise-saved").textContent = "saved, thank you";
      if (current) current.expertise = input.value;
    } catch (e) {
      $("#expertise-saved").textContent = "not saved: " + e.message;
    }
  });
}

const resume = location.origin + "/?rater=" + encodeURIComponent(rater);
$("#rater").textContent = rater;
$("#resume").textContent = resume;
$("#resume").href = resume;
api("/api/next").then(show).catch((e) => { $("#progress").textContent = "error: " + e.message; });
