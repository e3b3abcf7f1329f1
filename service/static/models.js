// "/models": the registered models with a preview render each, and the upload form.
// Previews load one at a time (each may wait for a worker's render); without a worker the
// cards keep a placeholder and the page stays usable.

import { ApiError, apiFetch, apiJson, blobUrl, notice } from "./api.js";
import { el, num, timeElement } from "./format.js";

const $ = (id) => document.getElementById(id);
const PREVIEW_SIDE_PX = 256;

function bytes(n) {
  if (n < 1024) return `${n} B`;
  if (n < 1024 ** 2) return `${(n / 1024).toFixed(1)} KiB`;
  return `${(n / 1024 ** 2).toFixed(1)} MiB`;
}

function extent(bounds) {
  const [lo, hi] = bounds;
  return lo.map((v, i) => num(hi[i] - v, 3)).join(" × ");
}

function card(model) {
  const facts = [
    ["Id", el("code", { text: model.id })],
    ["Size (x × y × z)", `${extent(model.bounds)} scene units`],
    ["Triangles", model.faces.toLocaleString()],
    ["Vertices", model.vertices.toLocaleString()],
    ["File", `${model.format.toUpperCase()}, ${bytes(model.size_bytes)}${model.textured ? ", textured" : ""}`],
    ["Registered", model.builtin ? "built in" : timeElement(model.created_at)],
  ];
  const placeholder = el("div", { class: "placeholder", "data-preview": model.id }, "Preview waiting…");
  const actions = el("div", { class: "buttons" },
    el("a", { class: "button", href: `/?model=${encodeURIComponent(model.id)}#new-estimate` }, "New estimate"));
  if (!model.builtin) {
    const remove = el("button", { type: "button", class: "danger" }, "Delete");
    remove.setAttribute("aria-label", `Delete ${model.name}`);
    remove.addEventListener("click", () => deleteModel(model));
    actions.append(remove);
  }
  return el("li", { class: "card", id: `model-${model.id}` },
    el("figure", { class: "preview" }, placeholder),
    el("h3", { text: model.name }),
    el("dl", { class: "facts" }, facts.flatMap(([k, v]) => [el("dt", { text: k }), el("dd", {}, v)])),
    actions);
}

/** Load each model's preview in turn; stop asking once no worker can render them. */
async function loadPreviews(models) {
  for (const model of models) {
    const slot = document.querySelector(`[data-preview="${CSS.escape(model.id)}"]`);
    if (!slot) continue;
    slot.textContent = "Rendering a preview…";
    try {
      const src = await blobUrl(`/models/${encodeURIComponent(model.id)}/preview.png?v=${model.sha256.slice(0, 16)}`);
      const img = el("img", {
        src, alt: `Preview render of ${model.name}`, width: PREVIEW_SIDE_PX, height: PREVIEW_SIDE_PX,
        "data-model": model.id,
      });
      slot.replaceWith(img);
    } catch (error) {
      const status = error instanceof ApiError ? error.status : 0;
      const why = status === 503 ? "No worker is running, so no preview yet."
        : status === 504 ? "The workers are busy; the preview comes later."
          : `No preview: ${error.message}`;
      slot.textContent = why;
      slot.classList.add("unavailable");
      if (status === 503) {
        for (const rest of document.querySelectorAll(".placeholder:not(.unavailable)")) {
          rest.textContent = why;
          rest.classList.add("unavailable");
        }
        return;
      }
    }
  }
}

async function loadModels() {
  const models = (await apiJson("/v1/models")).items;
  $("models").replaceChildren(...models.map(card));
  $("models-status").textContent = models.length
    ? `${models.length} model${models.length === 1 ? "" : "s"}.`
    : "No model is registered yet: the first worker registers demo-sat when it starts.";
  if (location.hash) document.getElementById(location.hash.slice(1))?.scrollIntoView();
  loadPreviews(models);
}

async function deleteModel(model) {
  if (!confirm(`Delete the model “${model.name}” (${model.id})? Queued estimates of it will fail.`)) return;
  try {
    await apiFetch(`/v1/models/${encodeURIComponent(model.id)}`, { method: "DELETE" });
    $("models-status").textContent = `Deleted ${model.name}.`;
    await loadModels();
  } catch (error) {
    notice(`Could not delete ${model.name}: ${error.message}`);
  }
}

function showUploadErrors(error) {
  const box = $("upload-errors");
  const items = error instanceof ApiError && error.errors.length
    ? error.errors.map((d) => `${(d.loc || []).filter((p) => p !== "body").join(".")}: ${d.msg}`)
    : [error.message];
  box.replaceChildren(el("p", { text: "The model was not registered:" }),
    el("ul", {}, items.map((m) => el("li", { text: m }))));
  box.hidden = false;
  $("model-file").setAttribute("aria-invalid", "true");
  $("model-file").focus();
}

async function upload(event) {
  event.preventDefault();
  const file = $("model-file").files[0];
  $("upload-errors").hidden = true;
  $("model-file").removeAttribute("aria-invalid");
  if (!file) {
    showUploadErrors(new Error("choose a mesh file"));
    return;
  }
  const body = new FormData();
  body.append("file", file, file.name);
  const name = $("model-name").value.trim();
  if (name) body.append("name", name);
  $("upload-button").disabled = true;
  $("upload-status").textContent = "Uploading and checking the mesh…";
  try {
    const response = await apiFetch("/v1/models", { method: "POST", body });
    const model = await response.json();
    $("upload-status").textContent = response.status === 201
      ? `Registered “${model.name}” as ${model.id}.`
      : `This file was registered before, as “${model.name}” (${model.id}).`;
    $("upload-form").reset();
    await loadModels();
  } catch (error) {
    $("upload-status").textContent = "";
    showUploadErrors(error);
  } finally {
    $("upload-button").disabled = false;
  }
}

$("upload-form").addEventListener("submit", upload);
loadModels().catch((error) => {
  $("models-status").textContent = `Could not load the models: ${error.message}`;
});
