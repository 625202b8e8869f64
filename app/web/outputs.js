// Admin view's outputs: the selected site's MQTT brokers and webhooks with how delivery to
// each goes (delivered, waiting, failed, the last error), read again every few seconds while
// the Admin tab is open, so a receiver that stopped answering shows as it happens.

const REFRESH_MS = 5000;

export class OutputsView {
  constructor(api, els, currentSite) {
    this.api = api;
    this.els = els;
    this.currentSite = currentSite;
    this.timer = null;
    els.refresh.addEventListener("click", () => this.refresh());
  }

  /** Read the outputs now and every few seconds while `visible`. */
  setVisible(visible) {
    clearInterval(this.timer);
    this.timer = null;
    if (!visible) return;
    this.refresh();
    this.timer = setInterval(() => this.refresh(), REFRESH_MS);
  }

  /** The selected site changed: show its outputs if the view is open. */
  siteChanged() {
    if (this.timer !== null) this.refresh();
  }

  async refresh() {
    const site = this.currentSite();
    const { list, status } = this.els;
    if (!site) {
      list.replaceChildren();
      status.textContent = "Pick a site.";
      return;
    }
    let outputs;
    try {
      outputs = await this.api.outputs(site);
    } catch (error) {
      status.textContent = `Could not read the outputs: ${error.message}`;
      status.dataset.state = "error";
      return;
    }
    if (site !== this.currentSite()) return;
    list.replaceChildren(...outputs.map(describe));
    status.dataset.state = "shown";
    status.textContent = outputs.length
      ? ""
      : "No outputs: PUT /v1/sites/{site_id}/outputs/{output_id} adds one (docs/outputs.md).";
  }
}

function describe(output) {
  const s = output.status;
  const item = document.createElement("li");
  item.className = "output";
  item.dataset.id = output.id;
  item.dataset.health = s.last_error ? "failing" : s.failed ? "lost" : "ok";
  const title = document.createElement("strong");
  title.textContent = `${output.id} · ${output.kind === "mqtt" ? "MQTT" : "webhook"}`;
  const where = document.createElement("span");
  where.className = "where";
  where.textContent = `${output.url} (${output.events.join(", ")})`;
  const counts = document.createElement("span");
  counts.className = "counts";
  counts.textContent =
    `${s.delivered} delivered · ${s.pending} waiting · ${s.failed} failed` +
    (s.last_ok_at ? ` · last delivery ${new Date(s.last_ok_at).toLocaleString()}` : "");
  item.append(title, where, counts);
  if (s.last_error) {
    const error = document.createElement("span");
    error.className = "error";
    error.textContent = s.last_error;
    item.append(error);
  }
  return item;
}
