// WonderVerse Studio's page: the JSON API (docs/studio.md) with the launch token as a Bearer header, the event
// stream read with fetch (EventSource cannot send a header), and the scene's 3D view: the viewer of
// `wonderverse view` in an iframe, reloaded whenever the scene's splats change. Text from the server is only ever
// set as textContent.

const query = new URLSearchParams(location.search);
const token = query.get("token") || sessionStorage.getItem("wonderverse-token") || "";
if (query.get("token")) {
  sessionStorage.setItem("wonderverse-token", token); // a reload keeps working; the address bar loses the token
  history.replaceState(null, "", location.pathname + location.hash);
}
const $ = (id) => document.getElementById(id);
// what the tests read: counts of events, the view's reloads, the last error shown
const S = (window.studio = { events: 0, progress: 0, lastEvent: null, scene: null, viewKey: null, viewLoads: 0,
  error: "", connected: false, job: null });

class ApiError extends Error {}

async function api(method, path, body) {
  const headers = { Authorization: `Bearer ${token}` };
  if (body !== undefined) headers["Content-Type"] = "application/json";
  const r = await fetch(path, { method, headers, body: body === undefined ? undefined : JSON.stringify(body) });
  let data = null;
  try { data = await r.json(); } catch { /* not JSON */ }
  if (!r.ok) {
    const err = new ApiError((data && data.error) || `HTTP ${r.status}`);
    err.status = r.status;
    err.data = data;
    throw err;
  }
  return data;
}

function showError(message) {
  S.error = message;
  $("error").textContent = message;
}

function cell(row, text, cls) {
  const td = document.createElement("td");
  td.textContent = text;
  if (cls) td.className = cls;
  row.appendChild(td);
  return td;
}

// ------------------------------------------------------------------------------------------- scenes

async function refreshScenes() {
  const { scenes } = await api("GET", "/api/scenes");
  const list = $("scenes");
  list.replaceChildren();
  for (const s of scenes) {
    const li = document.createElement("li");
    const b = document.createElement("button");
    b.textContent = s.name + (s.job ? ` (${s.job.kind}: ${s.job.state})` : "");
    b.className = s.name === S.scene ? "current" : "";
    b.onclick = () => select(s.name);
    li.appendChild(b);
    list.appendChild(li);
  }
  if (!S.scene && scenes.length) select(scenes[0].name);
}

function select(name) {
  S.scene = name;
  S.viewKey = null;
  $("view").src = "about:blank";
  $("log").textContent = "";
  $("scene-title").textContent = name;
  refreshScene();
  refreshScenes().catch(() => {});
}

let refreshing = null;
async function refreshScene() {
  if (!S.scene) return;
  if (refreshing) return refreshing.then(() => refreshScene());
  const name = S.scene;
  refreshing = (async () => {
    try {
      const info = await api("GET", `/api/scenes/${encodeURIComponent(name)}`);
      if (name !== S.scene) return;
      showScene(info);
    } catch (err) {
      if (err.status !== 404) showError(err.message);
    }
  })();
  await refreshing;
  refreshing = null;
}

function showScene(info) {
  $("prompt").textContent = info.prompt ? `“${info.prompt}”${info.seed != null ? ` (seed ${info.seed})` : ""}` : "";
  $("segments-count").textContent = String(info.segments.length);
  $("gaussians-count").textContent = info.gaussians == null ? "-" : String(info.gaussians);
  const body = $("segments");
  body.replaceChildren();
  for (const s of info.segments) {
    const row = document.createElement("tr");
    cell(row, s.id);
    cell(row, s.move);
    cell(row, s.words || "");
    cell(row, s.check, s.check).title = s.check_reasons.join("; ");
    cell(row, s.plan_following, s.plan_following).title = s.plan_reasons.join("; ");
    body.appendChild(row);
  }
  const files = $("files");
  files.replaceChildren();
  for (const f of info.files) {
    const a = document.createElement("a");
    a.href = `/scenes/${encodeURIComponent(info.name)}/files/${f.split("/").map(encodeURIComponent).join("/")}`;
    a.textContent = f.endsWith(".html") ? `${f} (open)` : f;
    if (f.endsWith(".html")) a.target = "_blank";
    else a.setAttribute("download", f.includes(".") ? f : `${f}.zip`);
    files.appendChild(a);
  }
  showJob(info.job || info.last_job);
  if (info.view_key && info.view_key !== S.viewKey) {
    S.viewKey = info.view_key;
    S.viewLoads += 1;
    $("view").src = `/scenes/${encodeURIComponent(info.name)}/view?key=${encodeURIComponent(info.view_key)}`;
  }
}

function showJob(job) {
  S.job = job;
  $("job-kind").textContent = job ? job.kind : "";
  $("job-state").textContent = job ? job.state : "none";
  $("job-step").textContent = job && job.step ? `step: ${job.step}` : "";
  $("job-progress").textContent = job && job.progress ? job.progress.line : "";
  $("job-error").textContent = job && job.error ? job.error : "";
  const busy = !!job && (job.state === "queued" || job.state === "running");
  $("extend").disabled = busy;
}

// ------------------------------------------------------------------------------------------- events

function onEvent(e) {
  S.events += 1;
  S.lastEvent = e;
  if (e.type === "progress") S.progress += 1;
  if (e.type === "job") refreshScenes().catch(() => {});
  if (e.scene !== S.scene) return;
  if (e.type === "log") {
    const log = $("log");
    log.textContent += e.line + "\n";
    log.scrollTop = log.scrollHeight;
  } else if (e.type === "progress") {
    $("job-step").textContent = `step: ${e.step}`;
    if (e.event === "progress") $("job-progress").textContent = e.line;
    if (e.event === "started") $("job-progress").textContent = e.description;
    if (e.event === "finished") {
      $("job-progress").textContent = `${e.step}: ${e.status} (${e.seconds.toFixed(1)} s)${e.detail ? " — " + e.detail : ""}`;
      refreshScene();
    }
  } else if (e.type === "job") {
    $("job-state").textContent = e.state;
    $("job-error").textContent = e.error || "";
    if (e.state === "failed" && e.error) showError(`${e.scene}: ${e.error}`);
    refreshScene();
  }
}

async function stream() {
  let since = 0;
  for (;;) {
    try {
      const r = await fetch(`/api/events?since=${since}`, { headers: { Authorization: `Bearer ${token}` } });
      if (!r.ok) {
        const data = await r.json().catch(() => ({}));
        showError(data.error || `events: HTTP ${r.status}`);
        $("connection").textContent = "not connected";
        return;
      }
      S.connected = true;
      $("connection").textContent = "live";
      const reader = r.body.pipeThrough(new TextDecoderStream()).getReader();
      let buffer = "";
      for (;;) {
        const { value, done } = await reader.read();
        if (done) break;
        buffer += value;
        let end;
        while ((end = buffer.indexOf("\n\n")) >= 0) {
          const chunk = buffer.slice(0, end);
          buffer = buffer.slice(end + 2);
          const data = chunk.split("\n").filter((l) => l.startsWith("data: ")).map((l) => l.slice(6)).join("\n");
          if (!data) continue;
          const event = JSON.parse(data);
          since = event.id;
          onEvent(event);
        }
      }
    } catch (err) {
      console.warn("event stream:", err);
    }
    S.connected = false;
    $("connection").textContent = "reconnecting…";
    await new Promise((resolve) => setTimeout(resolve, 2000));
  }
}

// ------------------------------------------------------------------------------------------- forms

$("create-form").onsubmit = async (ev) => {
  ev.preventDefault();
  showError("");
  const seed = $("new-seed").value.trim();
  const body = { name: $("new-name").value, prompt: $("new-prompt").value, preset: $("new-preset").value || null };
  if (seed !== "") body.seed = Number(seed);
  try {
    const { scene } = await api("POST", "/api/scenes", body);
    select(scene);
  } catch (err) {
    showError(err.message);
  }
};

$("extend-form").onsubmit = async (ev) => {
  ev.preventDefault();
  showError("");
  if (!S.scene) return showError("select a scene first");
  try {
    await api("POST", `/api/scenes/${encodeURIComponent(S.scene)}/extend`, { words: $("words").value });
    S.extendedAt = performance.now();
    refreshScene();
  } catch (err) {
    showError(err.message);
  }
};

$("rec-form").onsubmit = async (ev) => {
  ev.preventDefault();
  showError("");
  const name = $("rec-name").value;
  try {
    const { scene } = await api("POST", `/api/scenes/${encodeURIComponent(name)}/reconstruct`,
      { clips: $("rec-clips").value });
    select(scene);
  } catch (err) {
    showError(err.message);
  }
};

// a path dropped on the clips box (a file manager drops its URI): its path goes in as a line
$("rec-clips").addEventListener("drop", (ev) => {
  const uri = ev.dataTransfer.getData("text/uri-list") || ev.dataTransfer.getData("text/plain");
  if (!uri) return;
  ev.preventDefault();
  const paths = uri.split(/\r?\n/).filter((l) => l && !l.startsWith("#"))
    .map((l) => (l.startsWith("file://") ? decodeURIComponent(new URL(l).pathname) : l));
  $("rec-clips").value = [$("rec-clips").value.trim(), ...paths].filter(Boolean).join("\n");
});

if (!token) showError("no token: open the studio at the URL it printed when it started (…/?token=…)");
refreshScenes().catch((err) => showError(err.message));
stream();
