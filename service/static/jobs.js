// The list of recent estimates on "/": newest first, filtered by status, refreshed every few
// seconds while a job is queued or running (every half minute otherwise).

import { apiJson, notice } from "./api.js";
import { ACTIVE, badge, el, elapsed, num, seconds, timeElement } from "./format.js";

const PAGE_SIZE = 50;
const ACTIVE_REFRESH_MS = 2000;
const IDLE_REFRESH_MS = 30000;

const state = { jobs: [], cursor: null, modelNames: new Map(), timer: null };

/** The list's query for the chosen status filter (filtered by the API, so pages stay full). */
function filterQuery() {
  const filter = document.getElementById("status-filter").value;
  return filter ? `&status=${encodeURIComponent(filter)}` : "";
}

function row(job) {
  const id = el("a", { href: `/estimates/${job.id}`, title: job.id }, el("code", {}, job.id.slice(0, 8)));
  const outcome = job.outcome;
  const progress = job.progress;
  const iterations =
    job.status === "queued" ? "—" : `${progress.iteration} / ${progress.max_iterations}`;
  const duration = job.started_at ? seconds(elapsed(job.started_at, job.finished_at)) : "—";
  const model = state.modelNames.get(job.model_id);
  const status = job.error
    ? el("span", {}, badge(job.status), " ", el("small", { class: "muted", text: job.error.code }))
    : badge(job.status);
  return el(
    "tr",
    { "data-status": job.status, "data-id": job.id },
    el("td", {}, status),
    el("th", { scope: "row" }, id),
    el("td", { title: job.model_id }, model || job.model_id),
    el("td", { class: "num", text: iterations }),
    el("td", { class: "num", text: num(progress.cost, 3) }),
    el("td", { class: "num", text: outcome ? num(outcome.rotation_change_deg, 3) : "—" }),
    el("td", { class: "num", text: outcome ? num(outcome.translation_change, 3) : "—" }),
    el("td", { class: "num", text: duration }),
    el("td", {}, timeElement(job.created_at)),
  );
}

function render() {
  const filter = document.getElementById("status-filter").value;
  const shown = state.jobs.filter((job) => !filter || job.status === filter);
  document.getElementById("jobs").replaceChildren(...shown.map(row));
  document.getElementById("jobs-empty").hidden = shown.length > 0;
  document.getElementById("jobs-more").hidden = state.cursor === null;
  const active = state.jobs.filter((job) => ACTIVE.has(job.status)).length;
  const time = new Date().toLocaleTimeString();
  const what = `${shown.length} of ${state.jobs.length} loaded estimates shown`;
  const refresh = active
    ? `${active} queued or running: refreshing every ${ACTIVE_REFRESH_MS / 1000} s`
    : "refreshing every 30 s";
  document.getElementById("jobs-status").textContent = `${what} · updated ${time} · ${refresh}`;
  return active;
}

async function loadModelNames() {
  try {
    const models = await apiJson("/v1/models");
    for (const m of models.items) state.modelNames.set(m.id, m.name);
  } catch {
    // names are a nicety; ids are shown instead
  }
}

/** Reload the newest jobs (as many as are loaded now), then schedule the next refresh. */
async function refresh() {
  clearTimeout(state.timer);
  let active = 0;
  try {
    const limit = Math.min(100, Math.max(PAGE_SIZE, state.jobs.length));
    const page = await apiJson(`/v1/estimates?limit=${limit}${filterQuery()}`);
    if (state.jobs.length <= limit) {
      state.jobs = page.items;
      state.cursor = page.next_cursor;
    } else {
      // older pages were loaded by hand: keep them below the refreshed newest ones
      const fresh = new Set(page.items.map((j) => j.id));
      state.jobs = [...page.items, ...state.jobs.slice(limit).filter((j) => !fresh.has(j.id))];
    }
    active = render();
  } catch (error) {
    document.getElementById("jobs-status").textContent = `Could not load estimates: ${error.message}`;
  }
  state.timer = setTimeout(tick, active ? ACTIVE_REFRESH_MS : IDLE_REFRESH_MS);
}

function tick() {
  if (document.hidden) {
    document.addEventListener("visibilitychange", refresh, { once: true });
  } else {
    refresh();
  }
}

async function loadOlder() {
  try {
    const page = await apiJson(`/v1/estimates?limit=${PAGE_SIZE}&cursor=${state.cursor}${filterQuery()}`);
    const seen = new Set(state.jobs.map((j) => j.id));
    state.jobs.push(...page.items.filter((j) => !seen.has(j.id)));
    state.cursor = page.next_cursor;
    render();
  } catch (error) {
    notice(`Could not load older estimates: ${error.message}`);
  }
}

export async function initJobs() {
  document.getElementById("status-filter").addEventListener("change", () => {
    state.jobs = [];
    state.cursor = null;
    render();
    refresh();
  });
  document.getElementById("jobs-more").addEventListener("click", loadOlder);
  await loadModelNames();
  await refresh();
}
