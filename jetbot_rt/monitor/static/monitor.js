// The monitor page: the state from /events (server-sent events), the images from the MJPEG
// streams, one STOP (POST /stop). No library, no build step: the robot is often offline.
"use strict";

const $ = (id) => document.getElementById(id);
let over = false;

function fmt(v, digits, unit) {
  return v === null || v === undefined ? "–" : Number(v).toFixed(digits) + (unit || "");
}

function bar(id, value) {
  const v = Math.max(-1, Math.min(1, Number(value) || 0));
  const el = $(id);
  el.style.width = (Math.abs(v) * 50) + "%";
  el.style.left = v >= 0 ? "50%" : (50 + v * 50) + "%";
  $(id + "-v").textContent = fmt(value, 3);
}

function showState(s) {
  const el = $("state");
  el.textContent = s.state;
  el.className = "state " + (s.fault ? "fault" : s.state.split(" ")[0]);
  $("reason").textContent = s.reason || "";
}

function drawTrajectory(points, goal) {
  const canvas = $("trajectory");
  if (!points || points.length < 1) return;
  canvas.hidden = false;
  const ctx = canvas.getContext("2d");
  // the box around the path and the goal, at least 1 m across, centred
  const all = goal ? points.concat([goal]) : points;
  const xs = all.map((p) => p[0]), ys = all.map((p) => p[1]);
  const cx = (Math.min(...xs) + Math.max(...xs)) / 2, cy = (Math.min(...ys) + Math.max(...ys)) / 2;
  const span = Math.max(1, Math.max(...xs) - Math.min(...xs), Math.max(...ys) - Math.min(...ys)) * 1.2;
  const scale = Math.min(canvas.width, canvas.height) / span;
  const px = (p) => [canvas.width / 2 + (p[0] - cx) * scale, canvas.height / 2 - (p[1] - cy) * scale];
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  ctx.strokeStyle = "#4493f8";
  ctx.lineWidth = 2;
  ctx.beginPath();
  points.forEach((p, i) => { const [x, y] = px(p); i ? ctx.lineTo(x, y) : ctx.moveTo(x, y); });
  ctx.stroke();
  if (goal) {
    const [gx, gy] = px(goal);
    ctx.fillStyle = "#d62c2c";
    ctx.fillRect(gx - 5, gy - 5, 10, 10);
  }
  const [x, y] = px(points[points.length - 1]);
  ctx.fillStyle = "#fff";
  ctx.beginPath(); ctx.arc(x, y, 4, 0, 2 * Math.PI); ctx.fill();
}

function update(s) {
  showState(s);
  const r = s.record;
  if (r) {
    bar("mu-left", r.mu[0]); bar("mu-right", r.mu[1]);
    bar("cmd-left", r.cmd[0]); bar("cmd-right", r.cmd[1]);
    $("tick-ms").textContent = fmt(r.tick_ms, 2, " ms") + " (p99 " + fmt(s.tick_ms_p99, 2, " ms") + ")";
    $("infer-ms").textContent = fmt(r.infer_ms, 2, " ms");
    $("frame-age").textContent = fmt(r.frame_age_ms, 1, " ms");
    if (r.goal_distance !== undefined) {
      $("goal-row").hidden = false;
      $("goal").textContent = fmt(r.goal_distance, 2, " m");
    }
  }
  $("rate").textContent = fmt(s.measured_hz, 1, " Hz") + " (target " + fmt(s.target_hz, 0, " Hz") + ")";
  $("ticks").textContent = s.ticks;
  $("overruns").textContent = s.overruns;
  const st = s.stream;
  $("stream").textContent = st.frames_sent + " sent, " + st.frames_dropped + " dropped (slow clients)";
  const rec = s.recording;
  $("recording").textContent = !rec ? "off" : (rec.error ? "stopped: " + rec.error :
    rec.frames_written + " frames written, " + rec.frames_dropped + " dropped");
  if (s.trajectory) drawTrajectory(s.trajectory, s.goal);
  if (s.ended) end(s);
}

function end(s) {
  if (over) return;
  over = true;
  document.body.classList.add("over");
  const e = s.ended;
  const banner = $("ended");
  banner.hidden = false;
  banner.className = e.fault ? "fault" : "";
  banner.textContent = "The run ended" + (e.fault ? " with a safe stop (fault)" : "") + ": " +
    (e.reason || "stopped") + " — exit " + e.exit_code + ".";
  $("stop").disabled = true;
  $("stop").textContent = "STOPPED";
  $("state").textContent = "ended";
  events.close();
}

const events = new EventSource("/events");
events.onmessage = (m) => update(JSON.parse(m.data));
events.addEventListener("end", (m) => update(JSON.parse(m.data)));
events.onerror = () => {
  if (over) return;
  // The server is gone without saying how (the process was killed): say so, retry.
  $("state").textContent = "connection lost";
  $("state").className = "state fault";
};

$("stop").addEventListener("click", async () => {
  const button = $("stop");
  button.disabled = true;
  button.textContent = "STOPPING";
  try {
    const reply = await fetch("/stop", { method: "POST", credentials: "same-origin" });
    if (!reply.ok) throw new Error("HTTP " + reply.status);
  } catch (err) {
    button.disabled = false;
    button.textContent = "STOP";
    $("reason").textContent = "stop not confirmed (" + err.message + "): use jetbot-rt stop";
  }
});

// Hold-to-drive (jetbot-rt drive --input page, [monitor] drive = true): while a button is
// held, POST /drive every 100 ms; each command is valid for the run's deadman (0.3 s at most),
// so a released button, a hidden tab or a lost network stops the wheels within it.
let driving = null;
function release() {
  if (driving !== null) clearInterval(driving);
  driving = null;
}
function hold(mu) {
  release();
  const [left, right] = mu.split(",").map(Number);
  const send = () => fetch("/drive", {
    method: "POST", credentials: "same-origin", headers: { "Content-Type": "application/json" },
    body: JSON.stringify({ left, right }),
  }).catch(release);
  send();
  driving = setInterval(send, 100);
}
fetch("/state", { credentials: "same-origin" }).then((r) => r.json()).then((s) => {
  if (!s.drive) return;
  $("drive").hidden = false;
  for (const button of document.querySelectorAll("#drive button")) {
    button.addEventListener("pointerdown", (e) => { e.preventDefault(); hold(button.dataset.mu); });
    for (const name of ["pointerup", "pointercancel", "pointerleave"]) {
      button.addEventListener(name, release);
    }
  }
  window.addEventListener("blur", release);
  document.addEventListener("visibilitychange", release);
}).catch(() => {});
