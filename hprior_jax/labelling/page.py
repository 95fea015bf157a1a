"""The labelling page: HTML, CSS and a little JavaScript, served as one string (no build
step, no files to package)."""

PAGE = """<!doctype html>
<html lang="en">
<head>
<meta charset="utf-8">
<title>hprior label</title>
<style>
  body { font-family: system-ui, sans-serif; margin: 1.5em; background: #fafafa; }
  #clips { display: flex; gap: 1em; }
  figure { margin: 0; text-align: center; }
  video { width: 420px; background: #000; border-radius: 4px; }
  #buttons button { font-size: 1.05em; margin: 0.6em 0.4em 0 0; padding: 0.4em 0.8em; }
  #buttons button:disabled { opacity: 0.45; }
  #controls { margin-top: 0.6em; color: #333; }
  #goal { font-weight: 600; margin: 0.2em 0 0.8em 0; }
  #status { color: #555; margin-top: 0.8em; min-height: 1.2em; }
  kbd { border: 1px solid #aaa; border-radius: 3px; padding: 0 0.3em; background: #fff; }
</style>
</head>
<body>
<h2>Which clip is better? <small id="where"></small></h2>
<p id="goal"></p>
<p>Labeller: <input id="labeller" size="16"> &middot; <span id="progress"></span></p>
<div id="clips">
  <figure><video id="left" muted loop playsinline preload="auto"></video>
    <figcaption>left (<kbd>1</kbd>)</figcaption></figure>
  <figure><video id="right" muted loop playsinline preload="auto"></video>
    <figcaption>right (<kbd>2</kbd>)</figcaption></figure>
</div>
<div id="controls">
  speed <select id="speed"><option value="0.25">0.25x</option><option value="0.5">0.5x</option>
  <option value="1" selected>1x (real time)</option></select>
  <button id="pause">pause <kbd>space</kbd></button>
  <button id="back">&#9664; step <kbd>,</kbd></button>
  <button id="forward">step &#9654; <kbd>.</kbd></button>
  <span id="watch"></span>
</div>
<div id="buttons">
  <button data-answer="left">Left is better <kbd>1</kbd></button>
  <button data-answer="right">Right is better <kbd>2</kbd></button>
  <button data-answer="equal">Equally good <kbd>3</kbd></button>
  <button data-answer="skip">Can't tell <kbd>0</kbd></button>
  <button id="undo">Undo last <kbd>u</kbd></button>
</div>
<div id="status"></div>
<script>
const token = new URLSearchParams(location.search).get("token");
const headers = {"Content-Type": "application/json"};
if (token) headers["X-Hprior-Token"] = token;
const withToken = (url) => token ? url + "?token=" + encodeURIComponent(token) : url;
const $ = (id) => document.getElementById(id);
const left = $("left"), right = $("right");
let current = null, busy = false, seen = {left: false, right: false};
const answers = document.querySelectorAll("[data-answer]");
// an answer waits until both clips have played through once (a black box is no evidence)
function gate() {
  const ready = current && seen.left && seen.right;
  answers.forEach((b) => b.disabled = !ready);
  $("watch").textContent = !current || ready ? "" : "answers open once both clips have played through";
}
for (const [name, v] of [["left", left], ["right", right]]) {
  let last = 0;
  v.addEventListener("timeupdate", () => {
    if (v.currentTime < last || v.currentTime >= v.duration - 0.05) { seen[name] = true; gate(); }
    last = v.currentTime;
  });
}
const rate = () => Number($("speed").value);
$("speed").onchange = () => { left.playbackRate = right.playbackRate = rate(); };
function pauseOrPlay() {
  if (left.paused) { left.play(); right.play(); $("pause").firstChild.textContent = "pause "; }
  else { left.pause(); right.pause(); $("pause").firstChild.textContent = "play "; }
}
function step(frames) {  // paused, one control step at a time, both clips together
  left.pause(); right.pause(); $("pause").firstChild.textContent = "play ";
  const dt = current ? 1 / current.fps : 0.05;
  const t = Math.min(Math.max(left.currentTime + frames * dt, 0), left.duration || 0);
  left.currentTime = right.currentTime = t;
}
$("pause").onclick = pauseOrPlay;
$("back").onclick = () => step(-1);
$("forward").onclick = () => step(1);
$("labeller").value = localStorage.getItem("hprior-labeller") || "anonymous";
$("labeller").onchange = () => localStorage.setItem("hprior-labeller", $("labeller").value);

function show(progress) {
  $("progress").textContent = `round ${progress.round}: ${progress.answered} of ${progress.asked} answered`;
}
async function call(method, url, body) {
  const r = await fetch(withToken(url), {method, headers, body: body && JSON.stringify(body)});
  const data = await r.json();
  if (!r.ok) throw new Error(data.error || r.statusText);
  return data;
}
async function next() {
  const data = await call("GET", "/api/next");
  show(data.progress);
  current = data.query;
  seen = {left: false, right: false};
  gate();
  if (!current) {
    $("where").textContent = "";
    $("status").textContent = "Every query is answered. Thank you!";
    left.removeAttribute("src"); right.removeAttribute("src");
    return;
  }
  $("where").textContent = `${current.task}, round ${current.round}, query ${current.id}`;
  $("goal").textContent = current.goal ? "Goal: " + current.goal : "";
  let ready = 0;
  const start = () => { if (++ready === 2) { left.currentTime = right.currentTime = 0;
                                              left.playbackRate = right.playbackRate = rate();
                                              left.play(); right.play(); } };
  left.oncanplaythrough = right.oncanplaythrough = start;
  left.src = withToken(`/api/clip/${current.id}/1`);
  right.src = withToken(`/api/clip/${current.id}/2`);
}
// keep the two clips in step: the right one follows the left one
left.ontimeupdate = () => { if (Math.abs(right.currentTime - left.currentTime) > 0.1)
                              right.currentTime = left.currentTime; };
async function answer(choice) {
  if (!current || busy || !(seen.left && seen.right)) return;
  busy = true;
  try {
    await call("POST", "/api/answer", {id: current.id, answer: choice,
                                       labeller: $("labeller").value});
    $("status").textContent = `saved: ${current.id} = ${choice}`;
    await next();
  } catch (e) { $("status").textContent = "not saved: " + e.message; }
  busy = false;
}
async function undo() {
  try {
    const data = await call("POST", "/api/undo", {labeller: $("labeller").value});
    $("status").textContent = data.undone ? `undone: ${data.undone}` : "nothing to undo";
    await next();
  } catch (e) { $("status").textContent = "undo failed: " + e.message; }
}
document.querySelectorAll("[data-answer]").forEach(
  (b) => b.onclick = () => answer(b.dataset.answer));
$("undo").onclick = undo;
const keys = {"1": "left", "2": "right", "3": "equal", "0": "skip"};
document.addEventListener("keydown", (e) => {
  if (e.target.tagName === "INPUT") return;
  if (keys[e.key]) answer(keys[e.key]);
  else if (e.key === "u") undo();
  else if (e.key === " ") { e.preventDefault(); pauseOrPlay(); }
  else if (e.key === ",") step(-1);
  else if (e.key === ".") step(1);
});
next().catch((e) => $("status").textContent = e.message);
</script>
</body>
</html>
"""
