// "/": the list of recent estimates and the submit form.
import { initForm } from "./form.js";
import { initJobs } from "./jobs.js";
import { notice } from "./api.js";

for (const init of [initJobs, initForm]) {
  init().catch((error) => notice(`This page could not load: ${error.message}`));
}
