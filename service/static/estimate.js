// "/estimates/{id}": one estimate. While it runs, its progress streams in (SSE) with a live cost
// plot; once it ends, the result (result.js) or the error in words.

import { ApiError, apiFetch, apiJson, notice, readEvents } from "./api.js";
import { ACTIVE, ERROR_HINTS, badge, el, elapsed, num, seconds, timeElement } from "./format.js";
import { plot } from "./plots.js";
import { showResult } from "./result.js";

const $ = (id) => document.getElementById(id);
const jobId = $("estimate").dataset.jobId;
const RETRY_MS = 2000;
const POLL_MS = 3000;
const STREAM_RETRIES = 5;

const live = { points: [], controller: null, ended: false };

function showFacts(job) {
  const method = (job.request && job.request.options && job.request.options.method) || "default";
  const facts = [
    ["Model", el("a", { href: `/models#model-${job.model_id}` }, job.model_id)],
    ["Method", method],
    ["Created", timeElement(job.created_at)],
    ["Started", job.started_at ? timeElement(job.started_at) : "—"],
    ["Finished", job.finished_at ? timeElement(job.finished_at) : "—"],
    ["Duration", job.started_at ? seconds(elapsed(job.started_at, job.finished_at)) : "—"],
  ];
  $("facts").replaceChildren(...facts.flatMap(([k, v]) => [el("dt", { text: k }), el("dd", {}, v)]));
}

function showStatus(status, cancelRequested = false) {
  const node = $("status");
  node.className = `badge ${status}`;
  node.textContent = cancelRequested && status === "running" ? "running (stopping)" : status;
  document.title = `${status} · Estimate ${jobId.slice(0, 8)} · proxpose`;
}

function progressText(status, progress) {
  if (status === "queued") return "Queued: waiting for a free worker.";
  if (!progress || !progress.iteration) return "Running: rendering at the initial guess…";
  const stage = progress.stage ? ` (${progress.stage})` : "";
  const cost = progress.cost === null ? "" : `, cost ${num(progress.cost, 3)} px²`;
  return `Running: iteration ${progress.iteration} of at most ${progress.max_iterations}${stage}${cost}.`;
}

function showProgress(status, progress) {
  $("live").hidden = false;
  const bar = $("progress-bar");
  bar.max = progress ? progress.max_iterations : 1;
  bar.value = progress ? progress.iteration : 0;
  $("progress-text").textContent = progressText(status, progress);
  if (progress && progress.iteration && progress.cost !== null) {
    if (!live.points.some((p) => p.x === progress.iteration)) {
      live.points.push({
        x: progress.iteration, y: progress.cost, stage: progress.stage,
        tip: `iteration ${progress.iteration} (${progress.stage}): cost ${num(progress.cost)} px²`,
      });
    }
    $("live-plot").replaceChildren(plot({
      name: "live-cost", title: "Cost per iteration so far", unit: "cost, px²",
      points: live.points, log: true, summary: $("progress-text").textContent,
    }));
  }
}

function showFailure(job) {
  $("failure").hidden = false;
  const error = job.error || (job.status === "cancelled"
    ? { code: "cancelled", message: "This estimate was cancelled before it finished." }
    : { code: "unknown", message: `The estimate ended as ${job.status}.` });
  $("failure-title").textContent = job.status === "cancelled"
    ? "The estimate was cancelled" : "The estimate failed";
  $("failure-message").textContent = error.message;
  $("failure-hint").textContent = ERROR_HINTS[error.code] || "";
  $("failure-code").textContent = error.code;
}

function show(job) {
  showStatus(job.status, job.cancel_requested);
  showFacts(job);
  if (ACTIVE.has(job.status)) {
    showProgress(job.status, job.progress);
    $("cancel").disabled = job.cancel_requested;
    return;
  }
  live.ended = true;
  $("live").hidden = true;
  if (job.status === "succeeded" && job.result) showResult(job);
  else showFailure(job);
}

// ------------------------------------------------------------------ following a running job
async function follow() {
  for (let attempt = 0; attempt < STREAM_RETRIES && !live.ended; attempt++) {
    live.controller = new AbortController();
    try {
      await readEvents(`/v1/estimates/${jobId}/events`, onEvent, live.controller.signal);
    } catch (error) {
      if (live.ended || error.name === "AbortError") return;
      if (error instanceof ApiError && error.status < 500) throw error;
    }
    if (!live.ended) await new Promise((resolve) => setTimeout(resolve, RETRY_MS));
  }
  while (!live.ended) { // the stream keeps failing (a proxy?): poll instead
    show(await apiJson(`/v1/estimates/${jobId}`));
    await new Promise((resolve) => setTimeout(resolve, POLL_MS));
  }
}

function onEvent(name, data) {
  if (name === "status") {
    showStatus(data.status, data.cancel_requested);
    if (data.status === "running") showProgress("running", null);
  } else if (name === "progress") {
    showStatus("running");
    showProgress("running", data);
  } else if (name === "end") {
    show(data);
  }
}

async function cancel() {
  $("cancel").disabled = true;
  try {
    show(await (await apiFetch(`/v1/estimates/${jobId}`, { method: "DELETE" })).json());
  } catch (error) {
    notice(`Could not cancel: ${error.message}`);
  }
}

async function main() {
  $("cancel").addEventListener("click", cancel);
  let job;
  try {
    job = await apiJson(`/v1/estimates/${jobId}`);
  } catch (error) {
    if (error instanceof ApiError && error.status === 404) {
      showStatus("missing");
      $("failure").hidden = false;
      $("failure-title").textContent = "No such estimate";
      $("failure-message").textContent =
        "There is no estimate with this id: it never existed or it expired (finished estimates " +
        "are kept for the service's retention time).";
      $("failure-code").textContent = "not_found";
      return;
    }
    throw error;
  }
  show(job);
  if (ACTIVE.has(job.status)) await follow();
}

main().catch((error) => notice(`This page could not load the estimate: ${error.message}`));
