// What the pages of one job (an estimate, a track) share: following its event stream (with
// retries, then polling if the stream keeps failing), cancelling it, and its status badge.

import { ApiError, apiFetch, apiJson, notice, readEvents } from "./api.js";

const RETRY_MS = 2000;
const POLL_MS = 3000;
const STREAM_RETRIES = 5;

const pause = (ms) => new Promise((resolve) => setTimeout(resolve, ms));

/**
 * Follow the job at ``path`` until ``ended()``: its ``/events`` to ``onEvent(name, data)``,
 * reconnecting (with ``headers()``, e.g. a Last-Event-ID) when the stream drops; if it keeps
 * failing, poll the job and hand each state to ``show``.
 */
export async function followJob(path, { onEvent, show, ended, headers = () => ({}) }) {
  for (let attempt = 0; attempt < STREAM_RETRIES && !ended(); attempt++) {
    try {
      await readEvents(`${path}/events`, onEvent, new AbortController().signal, headers());
    } catch (error) {
      if (ended() || error.name === "AbortError") return;
      if (error instanceof ApiError && error.status < 500) throw error;
    }
    if (!ended()) await pause(RETRY_MS);
  }
  while (!ended()) { // the stream keeps failing (a proxy?): poll instead
    show(await apiJson(path));
    await pause(POLL_MS);
  }
}

/** The Cancel ``button``: DELETE the job at ``path`` and ``show`` its state after. */
export function wireCancel(button, path, show) {
  button.addEventListener("click", async () => {
    button.disabled = true;
    try {
      show(await (await apiFetch(path, { method: "DELETE" })).json());
    } catch (error) {
      notice(`Could not cancel: ${error.message}`);
    }
  });
}

/** The job at ``path``; null (the page then says so) when it does not exist. */
export async function loadJob(path, noun, jobId) {
  try {
    return await apiJson(path);
  } catch (error) {
    if (error instanceof ApiError && error.status === 404) {
      showMissing(noun, jobId);
      return null;
    }
    throw error;
  }
}

/** The status badge and the document title of the ``noun`` page of job ``jobId``. */
export function showStatus(node, noun, jobId, status, cancelRequested = false) {
  node.className = `badge ${status}`;
  node.textContent = cancelRequested && status === "running" ? "running (stopping)" : status;
  document.title = `${status} · ${noun} ${jobId.slice(0, 8)} · proxpose`;
}

const $ = (id) => document.getElementById(id);

/** The panel of a job that failed or was cancelled: its error in words, a hint, the code. */
export function showFailure(job, noun, cancelledMessage, hints) {
  $("failure").hidden = false;
  const error = job.error || (job.status === "cancelled"
    ? { code: "cancelled", message: cancelledMessage }
    : { code: "unknown", message: `The ${noun} ended as ${job.status}.` });
  $("failure-title").textContent = job.status === "cancelled"
    ? `The ${noun} was cancelled` : `The ${noun} failed`;
  $("failure-message").textContent = error.message;
  $("failure-hint").textContent = hints[error.code] || "";
  $("failure-code").textContent = error.code;
}

/** The same panel for a job that does not exist (or expired). */
export function showMissing(noun, jobId) {
  showStatus($("status"), noun[0].toUpperCase() + noun.slice(1), jobId, "missing");
  $("failure").hidden = false;
  $("failure-title").textContent = `No such ${noun}`;
  $("failure-message").textContent =
    `There is no ${noun} with this id: it never existed or it expired (finished ${noun}s ` +
    "are kept for the service's retention time).";
  $("failure-code").textContent = "not_found";
}
