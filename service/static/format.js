// Small helpers shared by the pages: element building, number, time and status formatting.

/** document.createElement with attributes (class, text, dataset and the rest) and children. */
export function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [name, value] of Object.entries(attrs)) {
    if (value === null || value === undefined || value === false) continue;
    if (name === "class") node.className = value;
    else if (name === "text") node.textContent = value;
    else node.setAttribute(name, value === true ? "" : String(value));
  }
  for (const child of children.flat()) {
    if (child === null || child === undefined) continue;
    node.append(child instanceof Node ? child : document.createTextNode(String(child)));
  }
  return node;
}

/** A number with ``digits`` significant digits, plain when moderate, exponent otherwise. */
export function num(x, digits = 4) {
  if (x === null || x === undefined || Number.isNaN(x)) return "—";
  if (x === 0) return "0";
  const a = Math.abs(x);
  if (a >= 1e-3 && a < 10 ** digits) return x.toPrecision(digits);
  if (a >= 1e-3 && a < 1e6) return x.toFixed(0);
  return x.toExponential(digits - 1);
}

/** A number with a fixed count of decimals (pose components read best aligned). */
export function fixed(x, decimals = 4) {
  return x === null || x === undefined ? "—" : x.toFixed(decimals);
}

export function seconds(s) {
  if (s === null || s === undefined) return "—";
  if (s < 60) return `${s.toFixed(s < 10 ? 1 : 0)} s`;
  const m = Math.floor(s / 60);
  if (m < 60) return `${m} min ${Math.round(s - 60 * m)} s`;
  return `${Math.floor(m / 60)} h ${m % 60} min`;
}

/** Seconds from ISO time ``a`` to ``b`` (now when null). */
export function elapsed(a, b = null) {
  if (!a) return null;
  return ((b ? Date.parse(b) : Date.now()) - Date.parse(a)) / 1000;
}

export function when(iso) {
  if (!iso) return "—";
  const d = new Date(iso);
  const today = new Date().toDateString() === d.toDateString();
  return today ? d.toLocaleTimeString() : d.toLocaleString();
}

export function timeElement(iso) {
  return el("time", { datetime: iso, title: iso, text: when(iso) });
}

export const ACTIVE = new Set(["queued", "running"]);

export function badge(status) {
  return el("span", { class: `badge ${status}`, text: status });
}

/** Rotation angle between unit quaternions [w, x, y, z], degrees: 2·acos|⟨a, b⟩|. */
export function angleBetweenDeg(a, b) {
  const dot = Math.abs(a.reduce((s, v, i) => s + v * b[i], 0));
  return (2 * Math.acos(Math.min(1, dot)) * 180) / Math.PI;
}

export function distance(a, b) {
  return Math.hypot(...a.map((v, i) => v - b[i]));
}

/** Plain-language advice for the engine's and the service's error codes. */
export const ERROR_HINTS = {
  invalid_image: "The image could not be read: send a PNG, JPEG or TIFF.",
  image_size_mismatch: "The image's size differs from the camera's width × height.",
  invalid_model: "The model file could not be loaded; register it again or try another format.",
  model_not_found: "The model was deleted or never registered; pick another on the Models page.",
  empty_render:
    "The model is not visible at the initial pose: check t (the target must be in front of " +
    "the camera, within the field of view) and the camera.",
  unlit_render:
    "The model is in view at the initial pose but the sun lights none of it: check " +
    "sun_direction (towards the sun, camera frame) and the model's orientation.",
  too_few_features:
    "The render at the initial pose and the image share too few features: bring the initial " +
    "pose closer, check the lighting (sun direction) and the camera.",
  render_failed: "The renderer failed on the worker; its log has the details.",
  timeout: "The estimate ran longer than the service's job time limit.",
  worker_stopped: "The worker was stopped while it ran this estimate; submit it again.",
  worker_lost: "The worker running this estimate stopped answering; submit it again.",
  internal_error: "The worker hit an unexpected error; its log has the details.",
  cancelled: "Cancelled on request.",
};
