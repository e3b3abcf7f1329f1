// Convergence plots as inline SVG: one quantity per iteration, accepted steps as dots, rejected
// steps as crosses, the coarse (PnP) stage shaded. Log scale for the cost, and for an error
// that spans more than LOG_SPAN; every point carries a tooltip (<title>).

const SVG = "http://www.w3.org/2000/svg";
const W = 440;
const H = 240;
const M = { left: 60, right: 14, top: 14, bottom: 42 };
const LOG_SPAN = 30;
let plotCount = 0;

function svg(tag, attrs = {}, text = null) {
  const node = document.createElementNS(SVG, tag);
  for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, String(v));
  if (text !== null) node.textContent = text;
  return node;
}

/** About ``count`` round tick values covering [lo, hi]. */
function linearTicks(lo, hi, count = 5) {
  const raw = (hi - lo) / count || 1;
  const mag = 10 ** Math.floor(Math.log10(raw));
  const step = [1, 2, 2.5, 5, 10].map((m) => m * mag).find((s) => s >= raw) || raw;
  const ticks = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi + step * 1e-9; v += step) {
    ticks.push(Number(v.toPrecision(12)));
  }
  return ticks;
}

/** Ticks for a log axis: the decades, or 1-2-5 steps, or round linear values in a short span. */
function logTicks(lo, hi) {
  const within = (mantissas) => {
    const ticks = [];
    for (let k = Math.floor(Math.log10(lo)); k <= Math.ceil(Math.log10(hi)); k++) {
      for (const m of mantissas) {
        const v = Number((m * 10 ** k).toPrecision(6));
        if (v >= lo * 0.999 && v <= hi * 1.001) ticks.push(v);
      }
    }
    return ticks;
  };
  for (const mantissas of [[1], [1, 2, 5]]) {
    const ticks = within(mantissas);
    if (ticks.length >= 3) return ticks;
  }
  return linearTicks(lo, hi, 4).filter((v) => v > 0);
}

function tickLabel(v, log) {
  if (v === 0) return "0";
  const a = Math.abs(v);
  if (log && (a < 1e-3 || a >= 1e5)) return v.toExponential(0);
  return String(Number(v.toPrecision(3)));
}

/** Whether to draw ``points`` on a log axis: always for ``true``, for "auto" when all are
 * positive and span more than LOG_SPAN. */
function wantsLog(points, log) {
  if (log !== "auto") return log;
  const ys = points.map((p) => p.y);
  return ys.length > 0 && ys.every((y) => y > 0) && Math.max(...ys) / Math.min(...ys) > LOG_SPAN;
}

/** The y axis; a linear one starts at 0 when ``zero``, else it spans the values (a range). */
function yScale(values, log, zero = true) {
  let lo = Math.min(...values);
  let hi = Math.max(...values);
  if (log) {
    const pad = Math.max(Math.log10(hi / lo) * 0.08, 0.15);
    lo = 10 ** (Math.log10(lo) - pad);
    hi = 10 ** (Math.log10(hi) + pad);
    const f = (v) => (Math.log10(hi) - Math.log10(v)) / (Math.log10(hi) - Math.log10(lo));
    return { log, ticks: logTicks(lo, hi), at: (v) => M.top + f(v) * (H - M.top - M.bottom) };
  }
  if (!zero) {
    const pad = (hi - lo) * 0.1 || Math.abs(hi) * 0.05 || 1;
    lo -= pad;
    hi += pad;
  } else lo = Math.min(0, lo);
  hi = hi > lo ? hi + (hi - lo) * 0.06 : lo + 1;
  const f = (v) => (hi - v) / (hi - lo);
  return { log, ticks: linearTicks(lo, hi), at: (v) => M.top + f(v) * (H - M.top - M.bottom) };
}

function cross(x, y, r) {
  return `M${x - r},${y - r}L${x + r},${y + r}M${x - r},${y + r}L${x + r},${y - r}`;
}

/**
 * A <figure> plotting ``points`` ({x, y, accepted, stage, tip}) of one quantity.
 * ``log``: true, false or "auto". ``summary``: a sentence for screen readers and the caption.
 * ``xLabel``: what x counts ("iteration", whose 0 is the initial guess, or "frame").
 */
export function plot({ name, title, unit, points, log = "auto", summary = "", xLabel = "iteration", zero = true }) {
  const id = `plot-${++plotCount}`;
  const finite = points.filter((p) => Number.isFinite(p.y));
  const useLog = wantsLog(finite, log);
  // a log axis has no place for 0 (e.g. the cost of an iteration that measured no features)
  const data = useLog ? finite.filter((p) => p.y > 0) : finite;
  const left = finite.filter((p) => !data.includes(p));
  const figure = document.createElement("figure");
  figure.className = "plot";
  figure.dataset.plot = name;
  const root = svg("svg", {
    viewBox: `0 0 ${W} ${H}`, role: "img", "aria-labelledby": `${id}-title ${id}-desc`,
    "data-points": data.length, class: `plot-svg ${name}`,
  });
  root.append(svg("title", { id: `${id}-title` }, title), svg("desc", { id: `${id}-desc` }, summary));
  const caption = document.createElement("figcaption");
  caption.textContent = title;
  figure.append(caption, root);
  if (left.length) {
    const init = xLabel === "iteration" ? "the initial guess" : "0";
    const which = left.map((p) => (p.x === 0 ? init : p.x)).join(", ");
    const note = document.createElement("p");
    note.className = "hint";
    note.textContent = `Not on the log scale (value 0): ${xLabel} ${which}.`;
    figure.append(note);
  }
  if (!data.length) return figure;

  const xs = finite.map((p) => p.x);
  const x0 = Math.min(...xs);
  const x1 = Math.max(x0 + 1, ...xs);
  const X = (x) => M.left + ((x - x0 + 0.5) / (x1 - x0 + 1)) * (W - M.left - M.right);
  const Y = yScale(data.map((p) => p.y), useLog, zero);
  const bottom = H - M.bottom;

  const coarse = finite.filter((p) => p.stage === "coarse").map((p) => p.x);
  if (coarse.length) {
    const a = X(Math.min(...coarse) - 0.5);
    const b = X(Math.max(...coarse) + 0.5);
    root.append(svg("rect", { x: a, y: M.top, width: b - a, height: bottom - M.top, class: "band" }));
    root.append(svg("text", { x: a + 4, y: bottom - 5, class: "band-label" }, "coarse"));
  }
  for (const v of Y.ticks) {
    const y = Y.at(v);
    root.append(svg("line", { x1: M.left, x2: W - M.right, y1: y, y2: y, class: "grid" }));
    root.append(svg("text", { x: M.left - 6, y: y + 4, class: "tick y" }, tickLabel(v, Y.log)));
  }
  const step = Math.max(1, Math.ceil((x1 - x0 + 1) / 10));
  for (let x = x0; x <= x1; x += step) {
    root.append(svg("line", { x1: X(x), x2: X(x), y1: bottom, y2: bottom + 4, class: "axis" }));
    root.append(svg("text", { x: X(x), y: bottom + 16, class: "tick x" }, x === 0 && xLabel === "iteration" ? "init" : x));
  }
  root.append(svg("line", { x1: M.left, x2: W - M.right, y1: bottom, y2: bottom, class: "axis" }));
  root.append(svg("line", { x1: M.left, x2: M.left, y1: M.top, y2: bottom, class: "axis" }));
  root.append(svg("text", { x: (M.left + W - M.right) / 2, y: H - 6, class: "label" }, xLabel));
  const yLabel = `${Y.log ? "log scale, " : ""}${unit}`;
  root.append(svg("text", {
    x: -(M.top + bottom) / 2, y: 14, transform: "rotate(-90)", class: "label",
  }, yLabel));

  const line = data.map((p) => `${X(p.x).toFixed(1)},${Y.at(p.y).toFixed(1)}`).join(" ");
  root.append(svg("polyline", { points: line, class: "line" }));
  for (const p of data) {
    const x = X(p.x);
    const y = Y.at(p.y);
    const mark = p.accepted === false
      ? svg("path", { d: cross(x, y, 4.5), class: "pt rejected" })
      : svg("circle", { cx: x, cy: y, r: 3.5, class: "pt" });
    mark.append(svg("title", {}, p.tip));
    root.append(mark);
  }
  return figure;
}
