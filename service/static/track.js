// "/tracks/{id}": one tracked sequence. While it runs, its frames stream in (SSE, one event per
// frame) and the plots and the frame table grow; once it ends, the overlay of a chosen frame,
// the worker's trajectory plot and the downloads (track.json, CSV), or the error in words.

import { blobUrl, notice } from "./api.js";
import { ACTIVE, ERROR_HINTS, el, elapsed, num, seconds, timeElement } from "./format.js";
import { followJob, loadJob, showFailure as failed, showStatus as setStatus, wireCancel } from "./job.js";
import { plot } from "./plots.js";

const $ = (id) => document.getElementById(id);
const jobId = $("track").dataset.jobId;
const STATUS_WORDS = { tracked: "tracked", reinitialised: "re-initialised", lost: "lost" };

const live = { frames: new Map(), total: 0, ended: false };

// ------------------------------------------------------------------ attitude
/** The rotation vector (deg) of the 3×3 rotation ``R``: axis × angle. */
function rotvecDeg(R) {
  const cos = Math.min(1, Math.max(-1, (R[0][0] + R[1][1] + R[2][2] - 1) / 2));
  const angle = Math.acos(cos);
  const w = [R[2][1] - R[1][2], R[0][2] - R[2][0], R[1][0] - R[0][1]];
  const s = Math.hypot(...w);
  if (s < 1e-12) return [0, 0, 0];
  return w.map((c) => (c / s) * angle * (180 / Math.PI));
}

/** R0ᵀ R: the rotation from the first frame's attitude to ``R``. */
function relative(R0, R) {
  return [0, 1, 2].map((i) => [0, 1, 2].map((j) => R0[0][i] * R[0][j] + R0[1][i] * R[1][j] + R0[2][i] * R[2][j]));
}

// ------------------------------------------------------------------ what the page shows
function showFacts(job) {
  const facts = [
    ["Model", el("a", { href: `/models#model-${job.model_id}` }, job.model_id)],
    ["Frames", String(job.progress.frames_total)],
    ["Created", timeElement(job.created_at)],
    ["Started", job.started_at ? timeElement(job.started_at) : "—"],
    ["Finished", job.finished_at ? timeElement(job.finished_at) : "—"],
    ["Duration", job.started_at ? seconds(elapsed(job.started_at, job.finished_at)) : "—"],
  ];
  $("facts").replaceChildren(...facts.flatMap(([k, v]) => [el("dt", { text: k }), el("dd", {}, v)]));
}

function showStatus(status, cancelRequested = false) {
  setStatus($("status"), "Track", jobId, status, cancelRequested);
}

function showProgress(status) {
  $("live").hidden = false;
  const done = live.frames.size;
  const bar = $("progress-bar");
  bar.max = live.total || 1;
  bar.value = done;
  $("progress-text").textContent = status === "queued"
    ? "Queued: waiting for a free worker."
    : `Running: ${done} of ${live.total} frames tracked.`;
}

function frameTip(f) {
  return `frame ${f.index} (${f.image}): ${STATUS_WORDS[f.status]}`;
}

function plots(frames) {
  const R0 = frames[0].pose.R;
  const pts = (y) => frames.map((f) => ({ x: f.index, y: y(f), accepted: f.status !== "lost", tip: `${frameTip(f)}, ${num(y(f), 4)}` }));
  const att = frames.map((f) => rotvecDeg(relative(R0, f.pose.R)));
  const byIndex = new Map(frames.map((f, i) => [f.index, att[i]]));
  const figures = [
    plot({ name: "range", title: "Range per frame", unit: "range, scene units", xLabel: "frame", log: false, zero: false,
      points: pts((f) => Math.hypot(...f.pose.t)), summary: `Range of ${frames.length} frames` }),
    ...["x", "y", "z"].map((axis, i) => plot({
      name: `attitude-${axis}`, title: `Attitude θ${axis} from frame 0`, unit: "degrees", xLabel: "frame", log: false,
      points: pts((f) => byIndex.get(f.index)[i]), summary: `Rotation-vector component ${axis} per frame`,
    })),
  ];
  if (frames.some((f) => f.errors)) {
    const withTruth = frames.filter((f) => f.errors);
    const errPts = (y) => withTruth.map((f) => ({ x: f.index, y: y(f), accepted: f.status !== "lost", tip: `${frameTip(f)}, ${num(y(f), 3)}` }));
    figures.push(
      plot({ name: "rotation-error", title: "Rotation error per frame", unit: "degrees", xLabel: "frame",
        points: errPts((f) => f.errors.rotation_deg), summary: "Rotation error against the truth" }),
      plot({ name: "translation-error", title: "Translation error per frame", unit: "% of range", xLabel: "frame",
        points: errPts((f) => f.errors.translation_pct_of_range), summary: "Translation error against the truth" }),
    );
  }
  $("plots").replaceChildren(...figures);
}

function framesTable(frames) {
  const truth = frames.some((f) => f.errors);
  const head = ["Frame", "Image", "Status", "Converged", "Time", "Renders", "Features", "Score",
    ...(truth ? ["Rotation error", "Translation error"] : [])];
  const rows = frames.map((f) => el("tr", { "data-status": f.status, "data-index": String(f.index) },
    el("th", { scope: "row" }, String(f.index)),
    el("td", {}, f.image),
    el("td", {}, el("span", { class: `badge ${f.status}` }, STATUS_WORDS[f.status])),
    el("td", {}, f.converged ? "yes" : "no"),
    el("td", { class: "num" }, seconds(f.seconds)),
    el("td", { class: "num" }, String(f.renders)),
    el("td", { class: "num" }, String(f.features)),
    el("td", { class: "num" }, num(f.alignment_score, 4)),
    ...(truth ? [
      el("td", { class: "num" }, f.errors ? `${num(f.errors.rotation_deg, 3)}°` : "—"),
      el("td", { class: "num" }, f.errors ? `${num(f.errors.translation_pct_of_range, 3)} %` : "—"),
    ] : [])));
  $("frames-table").replaceChildren(
    el("caption", { text: "Each frame's outcome, in order" }),
    el("thead", {}, el("tr", {}, head.map((h) => el("th", { scope: "col" }, h)))),
    el("tbody", {}, rows),
  );
}

function showFrames() {
  const frames = [...live.frames.values()].sort((a, b) => a.index - b.index);
  if (!frames.length) return;
  $("trajectory").hidden = false;
  $("frames-panel").hidden = false;
  plots(frames);
  framesTable(frames);
}

function addFrames(frames) {
  for (const f of frames) live.frames.set(f.index, f);
  showFrames();
}

function showSummary(s) {
  const errors = s.median_rotation_error_deg === null ? ""
    : ` Median error ${num(s.median_rotation_error_deg, 3)}° and ${num(s.median_translation_pct_of_range, 3)} % of range (max ${num(s.max_rotation_error_deg, 3)}°).`;
  $("summary").textContent = `${s.frames} frames: ${s.tracked} tracked, ${s.reinitialised} re-initialised, ` +
    `${s.lost} lost; ${num(s.frames_per_second, 3)} frames per second of engine time.${errors}`;
}

async function showOverlay(job, index) {
  const url = job.artifacts[`overlay_${index}`];
  const frame = live.frames.get(index);
  $("overlay").alt = `Frame ${index} in red over the render at its tracked pose in blue`;
  $("overlay-caption").textContent = `Frame ${index} (${frame.image}): ${STATUS_WORDS[frame.status]}`;
  $("overlay").src = await blobUrl(url);
}

async function showResult(job) {
  $("result").hidden = false;
  showSummary(job.result.summary);
  const select = $("frame-select");
  const indices = job.result.frames.map((f) => f.index).filter((k) => job.artifacts[`overlay_${k}`]);
  select.replaceChildren(...indices.map((k) => el("option", { value: String(k) }, `${k}: ${live.frames.get(k).image}`)));
  select.addEventListener("change", () => showOverlay(job, Number(select.value)).catch((e) => notice(e.message)));
  if (indices.length) await showOverlay(job, indices[0]);
  else $("overlay-figure").hidden = true;
  $("trajectory-png").src = await blobUrl(job.artifacts.trajectory);
  const json = $("download-track");
  json.href = `/v1/tracks/${jobId}/track.json`;
  json.download = `track-${jobId.slice(0, 8)}.json`;
  const table = $("download-csv");
  table.href = job.artifacts["track.csv"];
  table.download = `track-${jobId.slice(0, 8)}.csv`;
}

function showFailure(job) {
  failed(job, "track", `This track was cancelled after ${job.frames.length} of ${job.progress.frames_total} frames.`, ERROR_HINTS);
}

function show(job) {
  showStatus(job.status, job.cancel_requested);
  showFacts(job);
  live.total = job.progress.frames_total;
  addFrames(job.frames);
  if (ACTIVE.has(job.status)) {
    showProgress(job.status);
    $("cancel").disabled = job.cancel_requested;
    return;
  }
  live.ended = true;
  $("live").hidden = true;
  if (job.status === "succeeded" && job.result) showResult(job).catch((e) => notice(e.message));
  else showFailure(job);
}

// ------------------------------------------------------------------ following a running track
async function follow() {
  await followJob(`/v1/tracks/${jobId}`, {
    onEvent, show, ended: () => live.ended,
    headers: () => (live.frames.size ? { "Last-Event-ID": String(live.frames.size) } : {}),
  });
}

function onEvent(name, data) {
  if (name === "status") {
    showStatus(data.status, data.cancel_requested);
    if (data.status === "running") showProgress("running");
  } else if (name === "progress") {
    showStatus("running");
    live.total = data.frames_total;
    addFrames([data.frame]);
    showProgress("running");
  } else if (name === "end") {
    show(data);
  }
}

async function main() {
  wireCancel($("cancel"), `/v1/tracks/${jobId}`, show);
  const job = await loadJob(`/v1/tracks/${jobId}`, "track", jobId);
  if (!job) return;
  show(job);
  if (ACTIVE.has(job.status)) await follow();
}

main().catch((error) => notice(`This page could not load the track: ${error.message}`));
