// The JSON API as the pages use it: errors as ApiError, images as object URLs, Server-Sent
// Events read from a fetch stream. With API keys configured, the browser holds the key in the
// HttpOnly cookie that the key form (/session) sets, and same-origin fetches carry it; a 401
// (the cookie expired or was signed out elsewhere) sends the browser back to that form.

// Errors are RFC 9457 problem details: {type, title, status, detail, code, errors: [{loc, msg,
// type}]}; `errors` lists the bad fields (empty when the fault is not in a field).
export class ApiError extends Error {
  constructor(status, problem) {
    super(describeProblem(status, problem));
    this.status = status;
    this.problem = problem;
    this.code = problem.code || null;
    this.errors = Array.isArray(problem.errors) ? problem.errors : [];
  }
}

function describeProblem(status, problem) {
  if (Array.isArray(problem.errors) && problem.errors.length) {
    return problem.errors.map((d) => `${(d.loc || []).join(".")}: ${d.msg}`).join("; ");
  }
  if (typeof problem.detail === "string") return problem.detail;
  return `the service answered ${status}`;
}

/** fetch() of this service; answers other than 2xx/304 throw ApiError. */
export async function apiFetch(path, options = {}) {
  const response = await fetch(path, { credentials: "same-origin", ...options });
  if (!response.ok && response.status !== 304) {
    let problem = {};
    try {
      problem = await response.json();
    } catch {
      problem = { detail: response.statusText };
    }
    if (response.status === 401) signIn();
    if (response.status === 429) {
      const wait = response.headers.get("Retry-After");
      notice(`Too many submissions: try again${wait ? ` in ${wait} s` : " shortly"}.`);
    }
    throw new ApiError(response.status, problem);
  }
  return response;
}

export async function apiJson(path, options = {}) {
  return (await apiFetch(path, options)).json();
}

const blobUrls = new Map();

/** An object URL of the resource at ``path`` (fetched once per page). */
export async function blobUrl(path) {
  if (!blobUrls.has(path)) {
    const pending = apiFetch(path)
      .then((r) => r.blob())
      .then((b) => URL.createObjectURL(b));
    pending.catch(() => blobUrls.delete(path));
    blobUrls.set(path, pending);
  }
  return blobUrls.get(path);
}

/** An object URL for a JSON document, to offer as a download. */
export function jsonUrl(value) {
  const blob = new Blob([JSON.stringify(value, null, 2) + "\n"], { type: "application/json" });
  return URL.createObjectURL(blob);
}

/**
 * Read the text/event-stream at ``path``, calling ``onEvent(name, data)`` per event, until the
 * server closes it or ``signal`` aborts. Resolves when the stream ends. ``headers``: more
 * request headers (a reconnecting reader's Last-Event-ID).
 */
export async function readEvents(path, onEvent, signal, headers = {}) {
  const response = await apiFetch(path, { signal, headers: { Accept: "text/event-stream", ...headers } });
  const reader = response.body.pipeThrough(new TextDecoderStream()).getReader();
  let buffer = "";
  for (;;) {
    const { value, done } = await reader.read();
    if (done) return;
    buffer += value.replace(/\r\n?/g, "\n");
    let end;
    while ((end = buffer.indexOf("\n\n")) >= 0) {
      const block = buffer.slice(0, end);
      buffer = buffer.slice(end + 2);
      let name = "message";
      const data = [];
      for (const line of block.split("\n")) {
        if (line.startsWith("event:")) name = line.slice(6).trim();
        else if (line.startsWith("data:")) data.push(line.slice(5).trimStart());
      }
      if (data.length) onEvent(name, JSON.parse(data.join("\n")));
    }
  }
}

/** A key for Idempotency-Key (crypto.randomUUID needs a secure context; this does not). */
export function randomKey() {
  const bytes = crypto.getRandomValues(new Uint8Array(16));
  return Array.from(bytes, (b) => b.toString(16).padStart(2, "0")).join("");
}

// ------------------------------------------------------------------ notices and signing in
export function notice(message) {
  const box = document.getElementById("notice");
  box.textContent = message;
  box.hidden = !message;
}

/** Back to the key form, returning here once the key is accepted. */
function signIn() {
  notice("This service needs an API key: opening the key form…");
  location.assign(`/session?next=${encodeURIComponent(location.pathname + location.search)}`);
}
