// The submit form on "/": fields or a pasted REQUEST.json, defaults framing the chosen model,
// the camera sized from the chosen image, and the API's 422 answers shown on the fields.

import { ApiError, apiFetch, apiJson, randomKey } from "./api.js";
import { el } from "./format.js";
import { quaternionOf } from "./attitude.js";

const $ = (id) => document.getElementById(id);
const form = () => $("submit-form");

const CAMERA = ["width", "height", "fx", "fy", "cx", "cy", "skew"];
const FORM_OPTIONS = new Set(["method", "max_iterations"]);

// ------------------------------------------------------------------ fields ⇄ request
function read(id) {
  const value = $(id).value.trim();
  return value === "" ? null : Number(value);
}

function write(id, value) {
  $(id).value = value === null || value === undefined ? "" : String(value);
}

function readVector(prefix, n) {
  return Array.from({ length: n }, (_, i) => read(`${prefix}-${i}`));
}

function writeVector(prefix, values) {
  values.forEach((v, i) => write(`${prefix}-${i}`, v));
}

function fieldsToRequest() {
  const camera = {};
  for (const name of CAMERA) {
    const value = read(`cam-${name}`);
    if (value !== null || name !== "skew") camera[name] = value;
  }
  const request = {
    camera,
    initial_pose: { t: readVector("pose-t", 3), quaternion: readVector("pose-q", 4) },
    lighting: {
      sun_direction: readVector("sun", 3),
      sun_irradiance: read("sun-irradiance"),
      ambient: read("ambient"),
    },
    options: { method: $("method").value },
  };
  const cap = read("max-iterations");
  if (cap !== null) request.options.max_iterations = cap;
  const truthT = readVector("truth-t", 3);
  const truthQ = readVector("truth-q", 4);
  if ([...truthT, ...truthQ].some((v) => v !== null)) {
    request.ground_truth = { t: truthT, quaternion: truthQ };
  }
  return request;
}

/** Fill the fields from a request; returns what the fields cannot hold (nothing is changed
 * then). */
function requestToFields(request) {
  const problems = [];
  const extra = Object.keys(request.options || {}).filter((k) => !FORM_OPTIONS.has(k));
  if (extra.length) problems.push(`options the fields do not show: ${extra.join(", ")}`);
  const known = new Set(["model_id", "camera", "initial_pose", "lighting", "options", "ground_truth"]);
  const unknown = Object.keys(request).filter((k) => !known.has(k));
  if (unknown.length) problems.push(`unknown fields: ${unknown.join(", ")}`);
  if (!request.camera || !request.initial_pose) problems.push("camera and initial_pose are required");
  const initial = request.initial_pose && quaternionOf(request.initial_pose);
  const truth = request.ground_truth && quaternionOf(request.ground_truth);
  if (request.initial_pose && !initial) problems.push("initial_pose has no readable attitude");
  if (request.ground_truth && !truth) problems.push("ground_truth has no readable attitude");
  if (problems.length) return problems;

  for (const name of CAMERA) write(`cam-${name}`, request.camera[name]);
  writeVector("pose-t", request.initial_pose.t);
  writeVector("pose-q", initial);
  const lighting = request.lighting || {};
  writeVector("sun", lighting.sun_direction || [0, -0.6, -0.8]);
  write("sun-irradiance", lighting.sun_irradiance ?? 3.0);
  write("ambient", lighting.ambient ?? 0.02);
  const options = request.options || {};
  $("method").value = options.method || "default";
  write("max-iterations", options.max_iterations);
  writeVector("truth-t", request.ground_truth ? request.ground_truth.t : [null, null, null]);
  writeVector("truth-q", truth || [null, null, null, null]);
  if (request.ground_truth) $("truth-panel").open = true;
  if (request.model_id) selectModel(request.model_id);
  return [];
}

// ------------------------------------------------------------------ mode: fields or JSON
function mode() {
  return form().querySelector("input[name=mode]:checked").value;
}

function switchMode(event) {
  clearErrors();
  if (event.target.value === "json") {
    const request = { model_id: $("model").value || undefined, ...fieldsToRequest() };
    $("request-json").value = JSON.stringify(request, null, 2);
  } else {
    let problems;
    try {
      problems = requestToFields(JSON.parse($("request-json").value || "{}"));
    } catch (error) {
      problems = [`the JSON does not parse: ${error.message}`];
    }
    if (problems.length) {
      form().querySelector("input[name=mode][value=json]").checked = true;
      showErrors(problems.map((msg) => ({ path: "", msg: `Kept as JSON: ${msg}.` })));
      return;
    }
  }
  $("mode-fields").hidden = mode() !== "fields";
  $("mode-json").hidden = mode() !== "json";
}

// ------------------------------------------------------------------ models and defaults
function selectModel(id) {
  const select = $("model");
  if ([...select.options].some((o) => o.value === id)) select.value = id;
}

async function applyDefaults() {
  const id = $("model").value;
  if (!id) return;
  const width = read("cam-width") || 512;
  const height = read("cam-height") || 512;
  const status = $("submit-status");
  try {
    const request = await apiJson(`/models/${encodeURIComponent(id)}/request.json?width=${width}&height=${height}`);
    const truth = { t: readVector("truth-t", 3), q: readVector("truth-q", 4) };
    requestToFields(request);
    writeVector("truth-t", truth.t); // the truth is the user's, never a default
    writeVector("truth-q", truth.q);
    status.textContent = `Camera, pose and lighting set to frame ${id} in ${width}×${height} px.`;
  } catch (error) {
    status.textContent = `No defaults for ${id}: ${error.message}`;
  }
}

async function loadModels() {
  const select = $("model");
  const models = (await apiJson("/v1/models")).items;
  select.replaceChildren(
    ...models.map((m) => el("option", { value: m.id, text: `${m.name} (${m.id})` })),
  );
  if (!models.length) {
    select.append(el("option", { value: "", text: "no model registered yet" }));
    $("submit-status").textContent =
      "No model is registered yet: the first worker registers demo-sat when it starts, or " +
      "upload one on the Models page.";
  }
  const wanted = new URLSearchParams(location.search).get("model");
  if (wanted) selectModel(wanted);
  else if (models.some((m) => m.id === "demo-sat")) select.value = "demo-sat";
}

/** Set the camera's size from the chosen image, scaling the intrinsics (same field of view). */
async function sizeFromImage() {
  const file = $("image").files[0];
  if (!file) return;
  let bitmap;
  try {
    bitmap = await createImageBitmap(file);
  } catch {
    $("submit-status").textContent =
      "This browser cannot read the image's size (TIFF?): set the camera's width and height.";
    return;
  }
  const { width, height } = bitmap;
  bitmap.close();
  const oldWidth = read("cam-width");
  const oldHeight = read("cam-height");
  if (oldWidth === width && oldHeight === height) return;
  if (oldWidth && oldHeight) {
    const sx = width / oldWidth;
    const sy = height / oldHeight;
    for (const [name, s] of [["fx", sx], ["cx", sx], ["fy", sy], ["cy", sy], ["skew", sx]]) {
      const v = read(`cam-${name}`);
      if (v !== null) write(`cam-${name}`, name.startsWith("c") ? (v + 0.5) * s - 0.5 : v * s);
    }
  }
  write("cam-width", width);
  write("cam-height", height);
  $("submit-status").textContent = `Camera set to the image's ${width}×${height} px.`;
}

// ------------------------------------------------------------------ errors on the fields
function clearErrors() {
  for (const node of form().querySelectorAll("[aria-invalid], .invalid")) {
    node.removeAttribute("aria-invalid");
    node.classList.remove("invalid");
  }
  $("submit-errors").hidden = true;
  $("submit-errors").replaceChildren();
}

/** The visible element showing ``path`` (or its longest prefix that has one). */
function fieldFor(path) {
  const parts = path.split(".").filter((p) => p !== "");
  for (let n = parts.length; n >= 0; n--) {
    const key = parts.slice(0, n).join(".");
    for (const found of form().querySelectorAll(`[data-path="${CSS.escape(key)}"]`)) {
      if (!found.closest("[hidden]")) return found;
    }
  }
  return null;
}

function showErrors(errors) {
  const list = el("ul");
  let first = null;
  for (const { path, msg } of errors) {
    const field = fieldFor(path);
    const focusable = field && (field.matches("input, select, textarea") ? field
      : field.querySelector("input, select, textarea"));
    if (field) {
      field.setAttribute("aria-invalid", "true");
      field.classList.add("invalid");
    }
    first = first || focusable;
    const label = path ? el("code", { text: path }) : null;
    const item = focusable && focusable.id
      ? el("a", { href: `#${focusable.id}` }, label, label ? ": " : "", msg)
      : el("span", {}, label, label ? ": " : "", msg);
    list.append(el("li", {}, item));
  }
  const box = $("submit-errors");
  box.replaceChildren(el("p", { text: "The estimate was not submitted:" }), list);
  box.hidden = false;
  (first || box).focus?.();
}

function apiErrors(error) {
  if (!(error instanceof ApiError) || !error.errors.length) {
    return [{ path: "", msg: error.message }];
  }
  return error.errors.map((d) => {
    const loc = (d.loc || []).filter((p) => p !== "body" && p !== "request");
    return { path: loc.join("."), msg: d.msg };
  });
}

// ------------------------------------------------------------------ submit
async function submit(event) {
  event.preventDefault();
  clearErrors();
  const image = $("image").files[0];
  let request;
  if (mode() === "json") {
    try {
      request = JSON.parse($("request-json").value);
    } catch (error) {
      showErrors([{ path: "", msg: `the JSON does not parse: ${error.message}` }]);
      return;
    }
  } else {
    request = fieldsToRequest();
  }
  request = { model_id: $("model").value, ...request };
  if (!image) {
    showErrors([{ path: "image", msg: "choose the reference image" }]);
    return;
  }
  const body = new FormData();
  body.append("image", image, image.name);
  body.append("request", JSON.stringify(request));
  const button = $("submit-button");
  button.disabled = true;
  $("submit-status").textContent = "Submitting…";
  try {
    const headers = { "Idempotency-Key": randomKey() };
    const job = await (await apiFetch("/v1/estimates", { method: "POST", body, headers })).json();
    $("submit-status").textContent = `Submitted ${job.id.slice(0, 8)}; opening it…`;
    location.assign(`/estimates/${job.id}`);
  } catch (error) {
    $("submit-status").textContent = "";
    showErrors(apiErrors(error));
  } finally {
    button.disabled = false;
  }
}

async function prefillFrom(jobId) {
  const job = await apiJson(`/v1/estimates/${encodeURIComponent(jobId)}`);
  const request = { model_id: job.model_id, ...job.request };
  const problems = requestToFields(request);
  if (problems.length) {
    form().querySelector("input[name=mode][value=json]").checked = true;
    $("request-json").value = JSON.stringify(request, null, 2);
    $("mode-fields").hidden = true;
    $("mode-json").hidden = false;
  }
  $("submit-status").textContent =
    `Filled from estimate ${jobId.slice(0, 8)}: choose its reference image again to submit.`;
}

export async function initForm() {
  form().addEventListener("submit", submit);
  for (const radio of form().querySelectorAll("input[name=mode]")) {
    radio.addEventListener("change", switchMode);
  }
  $("image").addEventListener("change", sizeFromImage);
  $("model").addEventListener("change", applyDefaults);
  await loadModels();
  const from = new URLSearchParams(location.search).get("from");
  if (from) await prefillFrom(from);
  else await applyDefaults();
}
