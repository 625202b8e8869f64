// The Locus HTTP API as the dashboard uses it (see docs/api.md): one key, JSON in and out,
// errors turned into ApiError carrying the contract's {code, message, details}.

const KEY_STORAGE = "locus.key";

/** An HTTP error answer of the API. */
export class ApiError extends Error {
  constructor(status, code, message, details) {
    super(message);
    this.status = status;
    this.code = code;
    this.details = details;
  }
}

/** Return the key kept for this browser tab, or null. */
export function storedKey() {
  return sessionStorage.getItem(KEY_STORAGE);
}

/** Keep the key for this tab only: it is gone when the tab closes. */
export function storeKey(key) {
  sessionStorage.setItem(KEY_STORAGE, key);
}

export function forgetKey() {
  sessionStorage.removeItem(KEY_STORAGE);
}

export class Api {
  constructor(key) {
    this.key = key;
  }

  async request(method, path, { json, text, accept } = {}) {
    const headers = { Authorization: `Bearer ${this.key}` };
    let body;
    if (json !== undefined) {
      headers["Content-Type"] = "application/json";
      body = JSON.stringify(json);
    } else if (text !== undefined) {
      headers["Content-Type"] = "application/json";
      body = text;
    }
    if (accept) headers.Accept = accept;
    const response = await fetch(path, { method, headers, body });
    const answer = await response.text();
    let data = null;
    try {
      data = answer ? JSON.parse(answer) : null;
    } catch {
      data = null;
    }
    if (!response.ok) {
      const error = data?.error ?? {};
      throw new ApiError(
        response.status,
        error.code ?? "error",
        error.message ?? (answer || response.statusText),
        error.details ?? [],
      );
    }
    return data;
  }

  /** Return the sites this key may see (first page of up to 1000). */
  async sites() {
    const page = await this.request("GET", "/v1/sites?limit=1000");
    return page.items;
  }

  putSite(siteId, name) {
    return this.request("PUT", `/v1/sites/${enc(siteId)}`, { json: { name } });
  }

  floors(siteId) {
    return this.request("GET", `/v1/sites/${enc(siteId)}/floors`);
  }

  floor(siteId, floorId) {
    return this.request("GET", `/v1/sites/${enc(siteId)}/floors/${enc(floorId)}`);
  }

  /** Upload a floor map as the file's own text: the server judges it, bytes as sent. */
  putFloor(siteId, floorId, geojsonText) {
    return this.request("PUT", `/v1/sites/${enc(siteId)}/floors/${enc(floorId)}`, {
      text: geojsonText,
    });
  }

  accuracy(siteId, floorId, { tech, z, cell }) {
    const query = new URLSearchParams({ tech, z: String(z), cell: String(cell) });
    return this.request(
      "GET",
      `/v1/sites/${enc(siteId)}/floors/${enc(floorId)}/accuracy?${query}`,
      { accept: "application/json" },
    );
  }

  surveyGuidance(siteId, floorId) {
    return this.request(
      "GET",
      `/v1/sites/${enc(siteId)}/floors/${enc(floorId)}/survey-guidance?format=json`,
    );
  }

  heatmap(siteId, floorId, { from, to, cell }) {
    const query = new URLSearchParams({ from, to, cell: String(cell) });
    return this.request(
      "GET",
      `/v1/sites/${enc(siteId)}/floors/${enc(floorId)}/heatmap?${query}`,
      { accept: "application/json" },
    );
  }

  occupancy(siteId, zone, { from, to, bucket }) {
    const query = new URLSearchParams({ from, to, bucket_s: String(bucket) });
    return this.request("GET", `/v1/sites/${enc(siteId)}/zones/${enc(zone)}/occupancy?${query}`);
  }

  /** Return the site's outputs with their delivery status (first page of up to 100). */
  async outputs(siteId) {
    const page = await this.request("GET", `/v1/sites/${enc(siteId)}/outputs?limit=100`);
    return page.items;
  }

  /** Return a site's device's positions in [from, to] (ms), following next_from up to `cap` items. */
  async history(siteId, deviceId, from, to, { pageSize = 1000, cap = 50_000 } = {}) {
    const items = [];
    let next = from;
    while (next !== null && next <= to && items.length < cap) {
      const query = new URLSearchParams({ from: next, to, limit: pageSize });
      const path = `/v1/sites/${enc(siteId)}/devices/${enc(deviceId)}/positions`;
      const page = await this.request("GET", `${path}?${query}`);
      items.push(...page.items);
      next = page.next_from;
    }
    return { items: items.slice(0, cap), truncated: next !== null && next <= to };
  }

  /** Return "admin" or "reader" for this key (from GET /v1/keys/self). */
  async role() {
    const self = await this.request("GET", "/v1/keys/self");
    return self.role === "admin" ? "admin" : "reader";
  }

  /** Return the WebSocket URL of the site's position stream. */
  positionsUrl(siteId) {
    const scheme = location.protocol === "https:" ? "wss" : "ws";
    const query = new URLSearchParams({ site_id: siteId, key: this.key });
    return `${scheme}://${location.host}/v1/ws/positions?${query}`;
  }
}

function enc(part) {
  return encodeURIComponent(part);
}
