// A succeeded estimate on its page: the pose in every form, the 1-σ uncertainty, the errors
// against the truth, the convergence plots, the images, the request and the downloads.

import { blobUrl, jsonUrl, notice } from "./api.js";
import { angleBetweenDeg, distance, el, fixed, num, seconds } from "./format.js";
import { plot } from "./plots.js";

const $ = (id) => document.getElementById(id);

const REASONS = {
  step_below_epsilon: "the step fell below ε",
  cost_converged: "the cost stopped falling",
  pnp_converged: "the PnP steps became small",
  max_iterations: "it reached the iteration cap",
  stalled: "no step lowered the cost (stalled)",
};

const IMAGES = [
  ["overlay_1", "Overlay at the initial guess", "Reference (red) over the render (blue) at the initial guess"],
  ["overlay_2", "Overlay after the first step", "Reference (red) over the render (blue) after the first step"],
  ["overlay_final", "Overlay at the final estimate", "Reference (red) over the render (blue) at the final estimate; aligned structure is magenta"],
  ["difference", "Difference image", "Colour-mapped absolute difference between the reference and the final render"],
  ["final_render", "Render at the final estimate", "The model rendered at the final estimate"],
  ["convergence", "Convergence (worker's PNG)", "Convergence plot drawn by the worker: errors and log cost per iteration"],
];

function table(id, caption, head, rows) {
  const node = $(id);
  node.replaceChildren(
    el("caption", { text: caption }),
    el("thead", {}, el("tr", {}, head.map((h, i) => el("th", { scope: "col", class: i ? "num" : "" }, h)))),
    el("tbody", {}, rows.map((r) => el("tr", {}, el("th", { scope: "row" }, r[0]),
      r.slice(1).map((c) => el("td", { class: "num" }, c))))),
  );
}

function showPose(result) {
  const { pose, initial_pose: initial } = result;
  const rows = [
    ...["x", "y", "z"].map((a, i) => [`t${a}`, fixed(pose.t[i], 5), fixed(initial.t[i], 5)]),
    ...["w", "x", "y", "z"].map((a, i) => [`quaternion ${a}`, fixed(pose.quaternion[i], 7), fixed(initial.quaternion[i], 7)]),
    ...["1", "2", "3"].map((a, i) => [`Gibbs q${a}`, fixed(pose.q[i], 7), fixed(initial.q[i], 7)]),
  ];
  table("pose-table", "Pose, model → camera (t in scene units)", ["", "Estimate", "Initial guess"], rows);
  table("matrix-table", "Rotation matrix R of the estimate", ["", "col 1", "col 2", "col 3"],
    pose.R.map((row, i) => [`row ${i + 1}`, ...row.map((v) => fixed(v, 6))]));
  const rot = angleBetweenDeg(initial.quaternion, pose.quaternion);
  const shift = distance(initial.t, pose.t);
  const how = result.converged ? `Converged: ${REASONS[result.reason] || result.reason}`
    : `Not converged: ${REASONS[result.reason] || result.reason}`;
  $("verdict").textContent = `${how} after ${result.iterations} iterations and ` +
    `${result.renders} renders in ${seconds(result.seconds)}. The estimate is ${num(rot, 3)}° ` +
    `and ${num(shift, 3)} scene units from the initial guess.`;
}

function showUncertainty(result) {
  const c = result.covariance;
  if (!c) {
    table("sigma-table", "1-σ uncertainty", ["", ""], [["—", "none: the LM stage did not run"]]);
    $("covariance-table").replaceChildren();
    return;
  }
  const axes = ["x", "y", "z"];
  const stat = (list, i) => (list && list.length ? num(list[i], 3) : "—");
  table("sigma-table", "1-σ uncertainty (feature noise and model mismatch)",
    ["", "1σ", "of which noise"], [
    ...axes.map((a, i) => [`rotation about model ${a} (°)`, num(c.sigma_rotation_deg[i], 3),
      stat(c.statistical_sigma_rotation_deg, i)]),
    ...axes.map((a, i) => [`translation ${a} (scene units)`, num(c.sigma_translation[i], 3),
      stat(c.statistical_sigma_translation, i)]),
    ["residual σ (px)", num(c.residual_sigma_px, 3), ""],
  ]);
  const names = ["δq1", "δq2", "δq3", "δtx", "δty", "δtz"];
  table("covariance-table", "Covariance over [δq, δt]", ["", ...names],
    c.matrix.map((row, i) => [names[i], ...row.map((v) => num(v, 3))]));
}

function showErrors(result) {
  if (!result.errors) return;
  $("errors-block").hidden = false;
  const e = result.errors;
  const e0 = result.initial_errors || {};
  table("errors-table", "Errors against the ground truth", ["", "Initial guess", "Estimate"], [
    ["rotation (°)", num(e0.rotation_deg, 3), num(e.rotation_deg, 3)],
    ["translation (scene units)", num(e0.translation, 3), num(e.translation, 3)],
    ["translation (% of range)", num(e0.translation_pct_of_range, 3), num(e.translation_pct_of_range, 3)],
    ["SPEED score", num(e0.speed_score, 3), num(e.speed_score, 3)],
  ]);
}

// The fitted reflectance law: a Lommel–Seeliger share in Lambert, an Oren–Nayar roughness, or both.
function lawText(result) {
  const share = `${fixed(result.reflectance_share, 2)} Lommel–Seeliger`;
  if (!result.reflectance_roughness_deg) return `Lambert + ${share}`;
  const rough = `Oren–Nayar, roughness σ ${fixed(result.reflectance_roughness_deg, 1)}°`;
  return result.reflectance_share ? `${rough}, with ${share}` : rough;
}

function showRunFacts(result) {
  const facts = [
    ["Iterations", result.iterations], ["Renders", result.renders],
    ["Wall time", seconds(result.seconds)], ["Method", result.method],
    ["Features at the end", result.features], ["RMS residual", `${num(result.rms_residual_px, 3)} px`],
    ...(result.alignment_score === undefined ? []
      : [["Alignment score (NCC, 1 = identical)", num(result.alignment_score, 3)]]),
    ...(result.sun_direction
      ? [["Sun used (camera frame)", `[${result.sun_direction.map((v) => fixed(v, 4)).join(", ")}], ${fixed(result.sun_tilt_deg, 2)}° from the request's`]]
      : []),
    ...(result.reflectance_share || result.reflectance_roughness_deg
      ? [["Reflectance law", `${lawText(result)} (fitted from the image)`]]
      : []),
    ["Mitsuba variant", result.variant],
    ...Object.entries(result.timings_s).map(([k, v]) => [`Time in ${k}`, seconds(v)]),
  ];
  $("run-facts").replaceChildren(...facts.flatMap(([k, v]) => [el("dt", { text: k }), el("dd", { text: String(v) })]));
}

// ------------------------------------------------------------------ convergence
function series(history, value, initial, describe) {
  const points = history.map((h) => ({
    x: h.iteration, y: value(h), accepted: h.accepted, stage: h.stage,
    tip: `iteration ${h.iteration} (${h.stage}, ${h.accepted ? "accepted" : "rejected"}): ${describe(value(h))}`,
  }));
  if (initial !== null && initial !== undefined) {
    points.unshift({ x: 0, y: initial, accepted: true, stage: null, tip: `initial guess: ${describe(initial)}` });
  }
  return points;
}

function fell(points, unit) {
  if (points.length < 2) return "";
  return `From ${num(points[0].y, 3)} ${unit} to ${num(points.at(-1).y, 3)} ${unit} over ${points.length} points.`;
}

function showPlots(result) {
  const h = result.history;
  const truth = h.some((r) => r.rotation_error_deg !== null && r.rotation_error_deg !== undefined);
  const e0 = result.initial_errors || {};
  const figures = [];
  if (truth) {
    const rot = series(h, (r) => r.rotation_error_deg, e0.rotation_deg, (v) => `${num(v, 3)}°`);
    const tra = series(h, (r) => r.translation_error, e0.translation, (v) => `${num(v, 3)} scene units`);
    figures.push(plot({ name: "rotation", title: "Rotation error", unit: "degrees", points: rot, summary: fell(rot, "°") }));
    figures.push(plot({ name: "translation", title: "Translation error", unit: "scene units", points: tra, summary: fell(tra, "scene units") }));
  } else {
    const { quaternion: qf, t: tf } = result.pose;
    const init = result.initial_pose;
    const rot = series(h, (r) => angleBetweenDeg(r.pose.quaternion, qf), angleBetweenDeg(init.quaternion, qf), (v) => `${num(v, 3)}°`);
    const tra = series(h, (r) => distance(r.pose.t, tf), distance(init.t, tf), (v) => `${num(v, 3)} scene units`);
    figures.push(plot({ name: "rotation", title: "Rotation to the final estimate", unit: "degrees", points: rot, summary: fell(rot, "°") }));
    figures.push(plot({ name: "translation", title: "Translation to the final estimate", unit: "scene units", points: tra, summary: fell(tra, "scene units") }));
  }
  const cost = series(h, (r) => r.cost, null, (v) => `${num(v, 3)} px²`);
  figures.push(plot({ name: "cost", title: "Cost (mean squared feature residual)", unit: "px²", points: cost, log: true, summary: fell(cost, "px²") }));
  $("plots").replaceChildren(...figures);
  $("plots-note").hidden = truth;

  const head = ["Iteration", "Stage", "Step", "Cost (px²)", "‖δp‖", "λ", "Features", "Renders", "Time"];
  if (truth) head.push("Rotation error (°)", "Translation error");
  table("history-table", "Every iteration", head, h.map((r) => [
    String(r.iteration), r.stage, r.accepted ? "accepted" : "rejected", num(r.cost, 4),
    num(r.step_norm, 3), num(r.lambda, 3), String(r.features), String(r.renders), seconds(r.seconds),
    ...(truth ? [num(r.rotation_error_deg, 3), num(r.translation_error, 3)] : []),
  ]));
}

// ------------------------------------------------------------------ images and downloads
async function loadImage(img, link, url) {
  try {
    const src = await blobUrl(url);
    img.src = src;
    link.href = src;
  } catch (error) {
    img.alt = `${img.alt} (could not load: ${error.message})`;
    notice(`An image could not be loaded: ${error.message}`);
  }
}

function showImages(job) {
  const { width, height } = (job.request && job.request.camera) || {};
  const figures = [];
  for (const [name, caption, alt] of IMAGES) {
    const url = job.artifacts[name];
    if (!url) continue;
    const sized = name !== "convergence" && width;
    const img = el("img", { alt, "data-artifact": name, width: sized ? width : null, height: sized ? height : null, decoding: "async" });
    const link = el("a", { download: `${name}-${job.id.slice(0, 8)}.png`, class: "small" }, "Download PNG");
    figures.push(el("figure", { class: `image ${name}` }, img, el("figcaption", {}, caption, " · ", link)));
    loadImage(img, link, url);
  }
  $("images").replaceChildren(...figures);
}

function showRequest(job) {
  const request = { model_id: job.model_id, ...(job.request || {}) };
  $("request-json").textContent = JSON.stringify(request, null, 2);
  const result = $("download-result");
  result.href = jsonUrl(job.result);
  result.download = `result-${job.id.slice(0, 8)}.json`;
  const req = $("download-request");
  req.href = jsonUrl(request);
  req.download = `request-${job.id.slice(0, 8)}.json`;
  $("reuse-request").href = `/?from=${job.id}#new-estimate`;
}

export function showResult(job) {
  $("result").hidden = false;
  const result = job.result;
  showPose(result);
  showUncertainty(result);
  showErrors(result);
  showRunFacts(result);
  showPlots(result);
  showImages(job);
  showRequest(job);
}
