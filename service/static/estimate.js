// "/estimates/{id}": one estimate. While it runs, its progress streams in (SSE) with a live cost
// plot; once it ends, the result (result.js) or the error in words.

import { notice } from "./api.js";
import { ACTIVE, ERROR_HINTS, badge, el, elapsed, num, seconds, timeElement } from "./format.js";
import { followJob, loadJob, showFailure as failed, showStatus as setStatus, wireCancel } from "./job.js";
import { plot } from "./plots.js";
import { showResult } from "./result.js";

const $ = (id) => document.getElementById(id);
const jobId = $("estimate").dataset.jobId;

const live = { points: [], ended: false };

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
  setStatus($("status"), "Estimate", jobId, status, cancelRequested);
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
  failed(job, "estimate", "This estimate was cancelled before it finished.", ERROR_HINTS);
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
  await followJob(`/v1/estimates/${jobId}`, { onEvent, show, ended: () => live.ended });
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

async function main() {
  wireCancel($("cancel"), `/v1/estimates/${jobId}`, show);
  const job = await loadJob(`/v1/estimates/${jobId}`, "estimate", jobId);
  if (!job) return;
  show(job);
  if (ACTIVE.has(job.status)) await follow();
}

main().catch((error) => notice(`This page could not load the estimate: ${error.message}`));
