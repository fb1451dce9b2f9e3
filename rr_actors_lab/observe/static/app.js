// rr_actors observer: renders what /api/stream sends (server-sent events).
//
//   EventSource /api/stream ── "hello" ── mode, title, teaching mode on/off, hub instance
//                           ── "section" {key, version, value} ── tree | files | graph |
//                                         catalog/<name> | clock | ended
//                           ── "patch" {key, version, patch} ── what changed in a section
//                                         (applyPatch; the server's observe/_delta.py)
//                           ── "events" {events, missed} ── the tree's events (to_dict + text)
//   across hosts (hello.system): "hosts", "links", "graph", and host/<member>/tree |
//   host/<member>/catalog/<name> | host/<member>/ended; each event has its "member"; a
//   fault request names its "host" (observe/_hosts.py)
//   state ──(render, once per burst of messages)──► tree, catalogs, graph (cytoscape), timeline, log
//   a replay (hello.mode "replay", rr_actors_lab/teach/replay.py): a "replay" section (the step,
//   the story around it, what is in flight); its buttons, slider and story lines POST
//   /api/control {step}, and the step's sections come back on the stream as any change does
//
// Every request carries the page's token (the URL's ?token=; the server also sets a cookie).
// Everything from the server is shown through textContent (never parsed as HTML). The page
// keeps bounded state: at most MAX_EVENTS events, MAX_ROWS timeline rows, MAX_LOG log lines;
// a catalog shows PAGE resources per server at a time, and a graph of more than GRAPH_MAX
// resources is drawn as registrars only (the arrows between them counted). A tree of more
// than FOLD_OVER managers is drawn with its supervisors folded (each with its counts; a
// click opens it), CHILDREN_PAGE children and CARDS_PAGE catalogs at a time: what is drawn,
// and what a change redraws, does not grow with the tree (a patch keeps every unchanged
// node's object, so a change walks only the path to what changed).
"use strict";

(() => {
  const MAX_EVENTS = 500;
  const MAX_ROWS = 120;
  const MAX_LOG = 200;
  const MATCH_S = 0.05; // a delivery belongs to the send at (at - latency) within this
  const ORPHAN_S = 2; // a delivery whose send has not arrived this long after it (browser time) is shown alone
  const PAGE = 50; // resources of a server shown at a time
  const GRAPH_MAX = 200; // resources drawn one by one in the graph
  const FOLD_OVER = 50; // a tree of more managers is drawn with its supervisors folded
  const CHILDREN_PAGE = 100; // children of a supervisor drawn at a time
  const CARDS_PAGE = 50; // catalogs drawn at a time
  const GRAPH_REGISTRARS = 100; // more registrars: only those with resources or arrows drawn

  const state = {
    hello: null,
    instance: null,
    sections: {},
    lastSeq: 0,
    events: [],
    dirty: new Set(),
    scheduled: false,
    offset: 0, // server clock - browser clock, seconds
    restarts: {}, // child -> last restart count seen (to flash a restart)
    rows: [], // timeline rows, newest last
    orphans: [], // deliveries whose send has not arrived yet: {event, arrived}
    log: [],
    shown: {}, // "registrar/server" -> resources shown (paging)
    open: new Map(), // rowKey of a supervisor -> opened (true) or folded (false) by a click
    children: {}, // rowKey of a supervisor -> children shown (paging)
    cards: CARDS_PAGE, // catalogs shown
  };
  const token = (/(?:^|[?#&])token=([^&#]+)/.exec(location.search + location.hash) || [])[1] || "";

  // -- small DOM helpers ---------------------------------------------------------------
  function el(tag, props, ...children) {
    const node = document.createElement(tag);
    for (const [key, value] of Object.entries(props || {})) {
      if (value === undefined || value === null || value === false) continue;
      if (key === "class") node.className = value;
      else if (key === "text") node.textContent = value;
      else if (key.startsWith("data-")) node.setAttribute(key, String(value));
      else if (key === "onclick") node.addEventListener("click", value);
      else node.setAttribute(key, String(value));
    }
    for (const child of children) {
      if (child === null || child === undefined || child === false) continue;
      node.append(typeof child === "string" ? document.createTextNode(child) : child);
    }
    return node;
  }
  const $ = (id) => document.getElementById(id);
  const slug = (text) => String(text).replace(/\s+/g, "-");
  function clock(at) {
    const d = new Date(at * 1000);
    const pad = (n, w) => String(n).padStart(w, "0");
    return `${pad(d.getHours(), 2)}:${pad(d.getMinutes(), 2)}:${pad(d.getSeconds(), 2)}.${pad(d.getMilliseconds(), 3)}`;
  }
  function since(at) {
    const clockSection = state.sections.clock;
    if (!clockSection) return "";
    const t = at - clockSection.origin;
    return `${t < 0 ? "-" : "+"}${Math.abs(t).toFixed(2)} s`;
  }
  const ms = (s) => (s < 1 ? `${(s * 1000).toFixed(1)} ms` : `${s.toFixed(2)} s`);
  const plural = (n, word) => `${n} ${word}${n === 1 ? "" : "s"}`;
  const cut = (text, width) => (text.length <= width ? text : `${text.slice(0, width - 1)}…`);

  // -- the stream ----------------------------------------------------------------------
  function connect() {
    const source = new EventSource(`/api/stream?token=${encodeURIComponent(token)}`);
    source.addEventListener("hello", (e) => {
      const hello = JSON.parse(e.data);
      if (state.instance !== null && state.instance !== hello.instance) reset();
      state.instance = hello.instance;
      state.hello = hello;
      setConnection(true);
      renderHeader();
      schedule("tree", "files", "events", "catalogs");
    });
    source.addEventListener("section", (e) => {
      const { key, value } = JSON.parse(e.data);
      if (value === null) delete state.sections[key];
      else state.sections[key] = value;
      if (key === ownTreeKey() && value) state.offset = value.server_time - Date.now() / 1000;
      schedule(...kindsOf(key));
    });
    source.addEventListener("patch", (e) => {
      const { key, patch } = JSON.parse(e.data);
      const value = applyPatch(state.sections[key], patch);
      if (value === null) delete state.sections[key];
      else state.sections[key] = value;
      if (key === ownTreeKey() && value) state.offset = value.server_time - Date.now() / 1000;
      schedule(...kindsOf(key));
    });
    source.addEventListener("events", (e) => {
      const { events, missed } = JSON.parse(e.data);
      if (missed) addLog({ at: Date.now() / 1000, text: `${missed} events missed (the page fell behind)` });
      for (const event of events) {
        if (event.seq <= state.lastSeq) continue;
        state.lastSeq = event.seq;
        addEvent(event);
      }
      flushOrphans();
      schedule("events");
    });
    source.onerror = () => {
      if (state.sections.ended) source.close(); // (the final state stays on the page)
      setConnection(false);
    };
    source.onopen = () => setConnection(true);
  }

  // Across hosts, a section's key says which host it is of: host/<member>/<key>.
  const system = () => Boolean(state.hello && state.hello.system);
  const ownTreeKey = () => (system() ? `host/${state.hello.member}/tree` : "tree");
  function kindsOf(key) {
    if (key === "hosts") return ["tree", "catalogs", "graph"];
    if (key === "links") return ["tree"];
    const local = key.startsWith("host/") ? key.split("/").slice(2).join("/") : key;
    if (local.startsWith("catalog/")) return ["catalogs"];
    if (key.startsWith("host/") && local === "ended") return ["tree", "catalogs"];
    return [local];
  }
  function hostsList() {
    return (state.sections.hosts && state.sections.hosts.hosts) || [];
  }
  function hostOf(member) {
    return hostsList().find((h) => h.member === member) || null;
  }
  // Whether the page offers buttons for a host's managers: this host's teaching mode, or,
  // across hosts, that host's own allow_faults (it is asked, and decides, every time).
  function canFault(member) {
    if (state.hello.mode === "replay") return Boolean(state.hello.branches);
    if (!system()) return Boolean(state.hello.faults) && !state.sections.ended;
    const host = hostOf(member);
    return Boolean(host && host.allow_faults && host.state === "live" && !state.sections[`host/${member}/ended`]);
  }
  function catalogSection(registrar, member) {
    return system() ? state.sections[`host/${member}/catalog/${registrar}`] : state.sections[`catalog/${registrar}`];
  }
  const rowKey = (member, name) => `${member || ""}\u0000${name}`;

  // A patch (observe/_delta.py): {v} replaces; {d, x} changes and removes keys of a dict;
  // {l, k, x, i | o} changes, removes, inserts (or reorders) the rows of a list by their field k.
  function applyPatch(value, patch) {
    if ("v" in patch) return patch.v;
    if ("d" in patch) {
      const result = { ...value };
      for (const key of patch.x) delete result[key];
      for (const [key, sub] of Object.entries(patch.d)) result[key] = applyPatch(result[key], sub);
      return result;
    }
    const rows = new Map(value.map((row) => [row[patch.k], row]));
    for (const id of patch.x) rows.delete(id);
    let order = [...rows.keys()];
    for (const [id, sub] of Object.entries(patch.l)) rows.set(id, applyPatch(rows.get(id), sub));
    if (patch.o) order = patch.o;
    else for (const [index, id] of patch.i) order.splice(index, 0, id);
    return order.map((id) => rows.get(id));
  }

  function reset() {
    state.sections = {};
    state.lastSeq = 0;
    state.events = [];
    state.rows = [];
    state.orphans = [];
    state.log = [];
    state.restarts = {};
    treeRows.clear();
    drawn.clear();
    cardCache.clear();
    $("tree").replaceChildren();
  }

  // One badge says what the page is: live, disconnected, ended (the final state), offline.
  function setConnection(up) {
    const badge = $("connection");
    const mode = state.hello ? state.hello.mode : document.body.dataset.mode;
    let text = up ? "live" : "disconnected";
    if (mode === "backups") text = "offline";
    else if (mode === "replay" && up) text = "replay";
    else if (state.sections.ended) text = "ended";
    badge.textContent = text;
    badge.className = `badge ${text === "live" ? "up" : text === "disconnected" ? "down" : "still"}`;
  }

  function schedule(...keys) {
    for (const key of keys) state.dirty.add(key);
    if (state.scheduled) return;
    state.scheduled = true;
    setTimeout(render, 0); // (after the messages that arrived together)
  }

  const LISTS_EVERY = 250; // ms between two redraws of the timeline and the log
  let listsAt = 0;
  let listsLater = null;

  function render() {
    state.scheduled = false;
    const dirty = state.dirty;
    state.dirty = new Set();
    if (!state.hello) return;
    if (dirty.has("ended")) {
      setConnection(false);
      dirty.add("tree").add("catalogs"); // (the buttons go: there is nothing left to kill)
    }
    if (dirty.has("clock") || dirty.has("ended")) renderClock();
    if (dirty.has("tree") || dirty.has("files")) renderTree(); // at once: restarts show fast
    if (dirty.has("catalogs")) renderCatalogs();
    if (dirty.has("graph")) renderGraph();
    if (dirty.has("replay")) renderReplay();
    if (dirty.has("events") && listsLater === null) {
      const wait = Math.max(0, listsAt + LISTS_EVERY - Date.now());
      listsLater = setTimeout(() => {
        listsLater = null;
        listsAt = Date.now();
        renderTimeline();
        renderLog();
      }, wait);
    }
  }

  function renderHeader() {
    const hello = state.hello;
    $("title").textContent = hello.title;
    $("mode").textContent = hello.faults ? "teaching mode" : "";
    $("mode").hidden = !hello.faults;
    document.body.dataset.mode = hello.mode;
    $("replay-panel").hidden = hello.mode !== "replay";
    setConnection(true);
  }

  function renderClock() {
    const clockSection = state.sections.clock;
    const box = $("clock");
    if (!clockSection || state.hello.mode === "backups") {
      box.hidden = true;
      return;
    }
    const ended = state.sections.ended;
    const now = ended ? ended.at : Date.now() / 1000 + state.offset;
    box.hidden = false;
    box.textContent = `${clockSection.label} ${(now - clockSection.origin).toFixed(1)} s${ended ? " (ended)" : ""}`;
  }

  // -- notices and the confirmation ----------------------------------------------------
  let noticeTimer = null;
  function notice(text, refused) {
    const box = $("notice");
    box.textContent = text;
    box.className = refused ? "refused" : "";
    box.hidden = false;
    clearTimeout(noticeTimer);
    noticeTimer = setTimeout(() => (box.hidden = true), 8000);
  }

  function confirmThen(question, detail, label, action) {
    $("confirm-text").textContent = question;
    $("confirm-detail").textContent = detail;
    $("confirm-ok").textContent = label;
    const modal = $("confirm");
    modal.hidden = false;
    const close = () => {
      modal.hidden = true;
      $("confirm-ok").onclick = null;
      $("confirm-cancel").onclick = null;
    };
    $("confirm-ok").onclick = () => {
      close();
      action();
    };
    $("confirm-cancel").onclick = close;
    $("confirm-ok").focus();
  }

  async function fault(kind, body) {
    if (state.hello.mode === "replay") return branch(kind, body.child);
    try {
      const response = await fetch(`/api/faults/${kind}`, {
        method: "POST",
        headers: { "Content-Type": "application/json", "X-RR-Token": token },
        body: JSON.stringify(body),
      });
      const answer = await response.json();
      notice(answer.message, !answer.ok);
    } catch (error) {
      notice(`the request failed: ${error}`, true);
    }
  }

  // -- the supervision tree ------------------------------------------------------------
  const treeRows = new Map(); // rowKey -> {row, fields, node}: the rows drawn
  const drawn = new Map(); // rowKey of a supervisor drawn open -> its children's list
  let treeShape = "";
  let treeBig = false; // more than FOLD_OVER managers: supervisors start folded
  let painted = false;

  // Memoised by node object: a patch keeps the objects of unchanged nodes (applyPatch), so
  // a change costs the path to it, not the tree.
  const shapes = new WeakMap();
  function shapeOf(node) {
    let shape = shapes.get(node);
    if (shape === undefined) {
      shape = `${node.name}(${node.children.map((c) => (c.kind === "supervisor" ? shapeOf(c) : c.name)).join(",")})`;
      shapes.set(node, shape);
    }
    return shape;
  }
  const tallies = new WeakMap();
  function countsOf(node) {
    let counts = tallies.get(node);
    if (counts === undefined) {
      counts = { managers: 0, running: 0, down: 0, restarts: 0 };
      for (const child of node.children) {
        if (child.kind === "supervisor") {
          const sub = countsOf(child);
          counts.managers += sub.managers;
          counts.running += sub.running;
          counts.down += sub.down;
          counts.restarts += sub.restarts + (child.restarts || 0);
        } else {
          counts.managers += 1;
          if (child.state === "running") counts.running += 1;
          else counts.down += 1;
          counts.restarts += child.restarts || 0;
        }
      }
      tallies.set(node, counts);
    }
    return counts;
  }
  function summaryOf(node) {
    const c = countsOf(node);
    const down = c.managers - c.running;
    return `${plural(c.managers, "manager")} · ${c.running} running${down ? ` · ${down} not running` : ""} · ${plural(c.restarts, "restart")} below`;
  }
  function isOpen(node, root, member) {
    if (root) return true;
    const asked = state.open.get(rowKey(member, node.name));
    return asked === undefined ? !treeBig : asked;
  }
  function managersIn(node) {
    return countsOf(node).managers;
  }
  // The first time the tree (or the backups' list) is on the page: marks for the browser
  // tests and tools (performance.getEntriesByName("rr-tree-painted"): after the frame that
  // drew it); then the graph's library (its 400 kB, fetched early, run only now).
  function markPainted() {
    if (painted) return;
    painted = true;
    performance.mark("rr-tree-drawn");
    requestAnimationFrame(() => setTimeout(() => {
      performance.mark("rr-tree-painted");
      document.body.dataset.treePainted = "yes";
      const script = el("script", { src: "/static/vendor/cytoscape.min.js" });
      script.addEventListener("load", () => schedule("graph"));
      document.head.append(script);
    }, 0));
  }

  function renderTree() {
    if (state.hello.mode === "backups") return renderFiles();
    if (system()) return renderHosts();
    const tree = state.sections.tree;
    if (!tree) return;
    const shape = `${shapeOf(tree)}${state.sections.ended ? ":ended" : ""}`;
    if (shape !== treeShape) {
      treeShape = shape;
      treeBig = managersIn(tree) > FOLD_OVER;
      treeRows.clear();
      drawn.clear();
      $("tree").replaceChildren(el("ul", { class: "tree" }, buildNode(tree, true, null)));
    }
    updateNode(tree, true, null);
    markPainted();
  }

  // -- across hosts: one group per host (its member name), and the links between them ----
  const hostGroups = new Map(); // member -> {group, badge, faults, note}

  function renderHosts() {
    const hosts = hostsList();
    const shape = hosts
      .map((h) => {
        const tree = state.sections[`host/${h.member}/tree`];
        return `${h.member}:${canFault(h.member)}:${tree ? shapeOf(tree) : "-"}`;
      })
      .join("|");
    if (shape !== treeShape) {
      treeShape = shape;
      treeRows.clear();
      hostGroups.clear();
      treeBig = hosts.reduce((sum, h) => {
        const tree = state.sections[`host/${h.member}/tree`];
        return sum + (tree ? managersIn(tree) : 0);
      }, 0) > FOLD_OVER;
      drawn.clear();
      const groups = hosts.map((h) => buildHost(h));
      $("tree").replaceChildren(
        el("div", { class: "links-box" }, el("h3", { text: "Links between hosts" }), el("ul", { id: "links" })),
        ...(groups.length ? groups : [el("p", { class: "muted", text: "Waiting for the hosts…" })]),
      );
      markPainted();
    }
    for (const h of hosts) {
      const entry = hostGroups.get(h.member);
      if (!entry) continue;
      entry.group.dataset.state = h.state;
      entry.group.dataset.faults = h.allow_faults ? "yes" : "no";
      entry.badge.textContent = h.state;
      entry.badge.className = `badge host-state host-${h.state}`;
      entry.faults.textContent = h.allow_faults ? "faults allowed" : "no faults";
      entry.note.textContent = h.state === "live" ? "" : h.state === "joining" ? "joining: asking for its state…" : `stale since ${clock(h.since)} (${((Date.now() / 1000 + state.offset) - h.since).toFixed(1)} s ago): ${h.why}; last known state shown`;
      const tree = state.sections[`host/${h.member}/tree`];
      if (tree) updateNode(tree, true, h.member);
    }
    renderLinks();
  }

  function buildHost(h) {
    const badge = el("span", { class: "badge host-state" });
    const faults = el("span", { class: "badge host-faults" });
    const note = el("div", { class: "stale-note" });
    const tree = state.sections[`host/${h.member}/tree`];
    const group = el(
      "div",
      { class: "host", "data-member": h.member },
      el("h3", {}, el("span", { class: "member", text: h.member }), " ", badge, " ", faults, " ",
        el("small", { text: `${h.title || ""}${h.pid ? ` · pid ${h.pid}` : ""}${h.here ? " · this page's host" : ""}` })),
      note,
      tree ? el("ul", { class: "tree" }, buildNode(tree, true, h.member)) : el("p", { class: "muted", text: "no tree known yet" }),
    );
    hostGroups.set(h.member, { group, badge, faults, note });
    return group;
  }

  function renderLinks() {
    const list = $("links");
    if (!list) return;
    const links = state.sections.links || [];
    const items = links.map((l) =>
      el("li", { "data-link": l.id, "data-up": l.up ? "yes" : "no", class: l.up ? "link-up" : "link-cut" },
        el("span", { class: "member", text: l.a }), " ⇄ ", el("span", { class: "member", text: l.b }), ": ",
        el("span", { class: `badge ${l.up ? "state-running" : "state-gave-up"}`, text: l.up ? "up" : "cut" }),
        l.up ? "" : ` since ${l.since ? clock(l.since) : "?"}${l.since ? ` (${((Date.now() / 1000 + state.offset) - l.since).toFixed(1)} s ago)` : ""}: ${l.why}`),
    );
    list.replaceChildren(...(items.length ? items : [el("li", { class: "muted", text: "one host only so far" })]));
  }

  function buildNode(node, root, member) {
    const fields = {
      state: el("span", { class: "badge state", "data-field": "state" }),
      pid: el("span", { class: "mono", "data-field": "pid" }),
      restarts: el("span", { class: "restarts", "data-field": "restarts" }),
      countdown: el("span", { class: "countdown", "data-field": "countdown" }),
      exit: el("span", { class: "exit", "data-field": "last-exit" }),
    };
    const isManager = node.kind === "manager";
    const what = isManager
      ? `${node.isolation} manager · ${node.restart}`
      : `supervisor · ${node.strategy} · at most ${node.max_restarts} restarts in ${node.period} s`;
    const key = rowKey(member, root ? "\u0000root" : node.name);
    const open = !isManager && isOpen(node, root, member);
    if (!isManager) fields.summary = el("span", { class: "summary", "data-field": "summary" });
    const toggle = isManager || root ? null : el("button", {
      class: "fold",
      "data-fold": node.name,
      "aria-expanded": open ? "true" : "false",
      title: open ? "fold: hide its children" : "open: show its children",
      text: open ? "\u25BE" : "\u25B8",
      onclick: () => {
        state.open.set(rowKey(member, node.name), !isOpen(node, false, member));
        treeShape = ""; // (drawn again, with the rows it now shows)
        schedule("tree");
      },
    });
    const row = el(
      "div",
      { class: "node", "data-child": node.name, "data-kind": node.kind, "data-open": isManager ? undefined : open ? "yes" : "no" },
      toggle,
      el("span", { class: "name", text: node.name }),
      el("span", { class: "what", text: what }),
      fields.state,
      fields.pid,
      root ? null : fields.restarts,
      fields.countdown,
      isManager && node.isolation === "process" && canFault(member) ? faultButtons(node.name, member) : null,
      fields.summary,
      fields.exit,
    );
    treeRows.set(key, { row, fields, node: null });
    const item = el("li", {}, row);
    if (open) item.append(childrenList(node, member, key));
    return item;
  }

  // An open supervisor's children: CHILDREN_PAGE at a time, then a button for more.
  function childrenList(node, member, key) {
    const shown = Math.min(node.children.length, state.children[key] || CHILDREN_PAGE);
    const list = el("ul", {}, ...node.children.slice(0, shown).map((c) => buildNode(c, false, member)));
    if (shown < node.children.length)
      list.append(el("li", {}, el("button", {
        class: "more",
        "data-more-children": node.name,
        text: `show ${Math.min(CHILDREN_PAGE, node.children.length - shown)} more (${shown} of ${node.children.length} shown)`,
        onclick: () => {
          state.children[key] = shown + CHILDREN_PAGE;
          treeShape = "";
          schedule("tree");
        },
      })));
    drawn.set(key, shown);
    return list;
  }

  function faultButtons(name, member) {
    const pidOf = () => {
      const entry = treeRows.get(rowKey(member, name));
      return entry ? Number(entry.row.dataset.pid) : NaN;
    };
    const button = (label, title, kind, question, detail) =>
      el("button", {
        class: "danger",
        "data-fault": kind,
        title,
        text: label,
        onclick: () => {
          const pid = pidOf();
          if (!pid) return notice(`${name} has no process right now`, true);
          const on = member ? ` on ${member}` : "";
          confirmThen(question(pid) + on, detail, label, () => fault(kind, member ? { child: name, pid, host: member } : { child: name, pid }));
        },
      });
    if (state.hello.mode === "replay")
      return el(
        "span",
        { class: "faults" },
        button("kill", "run the seed again, its process killed right after this step", "kill", () => `Kill ${name} after this step?`,
          "The seed runs again with that kill (kill_manager after this step's event); the steps before it stay as they were."),
        button("cut", "run the seed again, its connections cut right after this step", "cut", () => `Cut ${name}'s links after this step?`,
          "The seed runs again with that cut (cut_connections after this step's event): every link to it closes."),
      );
    return el(
      "span",
      { class: "faults" },
      button("kill", "SIGKILL its process", "kill", (pid) => `SIGKILL ${name} (pid ${pid})?`,
        "Its supervisor sees the exit from the process sentinel and restarts it by its policy."),
      button("hang", "SIGSTOP its process", "hang", (pid) => `SIGSTOP ${name} (pid ${pid})?`,
        "It hangs: its heartbeat stops, and after its hang time the supervisor kills and restarts it. Resume sends SIGCONT before that."),
      button("resume", "SIGCONT its process", "resume", (pid) => `SIGCONT ${name} (pid ${pid})?`,
        "A process stopped by hang runs again."),
    );
  }

  // Only the rows drawn, and only where the node's object changed (a patch keeps the others).
  function updateNode(node, root, member) {
    const key = rowKey(member, root ? "\u0000root" : node.name);
    const entry = treeRows.get(key);
    if (!entry || entry.node === node) return;
    entry.node = node;
    {
      const { row, fields } = entry;
      const stateClass = `state-${slug(node.state)}`;
      row.className = `node ${stateClass}${row.classList.contains("flash") ? " flash" : ""}`;
      row.dataset.state = node.state;
      row.dataset.pid = node.pid || "";
      row.dataset.restarts = node.restarts || 0;
      row.dataset.restartDue = node.restart_due || "";
      fields.state.textContent = node.state;
      fields.state.className = `badge state ${stateClass}`;
      fields.pid.textContent = node.pid ? `pid ${node.pid}` : "";
      fields.restarts.textContent = root ? "" : plural(node.restarts || 0, "restart");
      fields.exit.textContent = node.last_exit ? `last exit: ${node.last_exit}` : node.gave_up ? `gave up: ${node.gave_up}` : "";
      const before = state.restarts[rowKey(member, node.name)];
      if (!root && before !== undefined && (node.restarts || 0) > before) flash(row);
      if (!root) state.restarts[rowKey(member, node.name)] = node.restarts || 0;
      if (fields.summary) {
        const below = countsOf(node).restarts;
        const seen = state.restarts[`${key}\u0000below`];
        fields.summary.textContent = summaryOf(node);
        row.dataset.below = below;
        if (!root && seen !== undefined && below > seen && row.dataset.open === "no") flash(row);
        state.restarts[`${key}\u0000below`] = below;
      }
    }
    const shown = drawn.get(key);
    if (shown === undefined) return;
    for (const child of node.children.slice(0, shown)) updateNode(child, false, member);
  }

  function flash(row) {
    row.classList.remove("flash");
    void row.offsetWidth; // restart the animation
    row.classList.add("flash");
  }

  function tickCountdowns() {
    const now = Date.now() / 1000 + state.offset;
    for (const { row, fields } of treeRows.values()) {
      const due = Number(row.dataset.restartDue);
      fields.countdown.textContent =
        due && row.dataset.state === "restarting" ? `restart in ${Math.max(0, due - now).toFixed(1)} s` : "";
    }
  }

  function renderFiles() {
    const files = state.sections.files;
    $("tree-heading").textContent = "Backups (read-only)";
    if (!files) return;
    const rows = files.files.map((f) =>
      el(
        "tr",
        { "data-registrar": f.registrar },
        el("td", { text: f.registrar }),
        el("td", { class: "mono", text: f.path }),
        el("td", { text: f.error ? "unreadable" : `schema ${f.schema_version}` }),
        el("td", { text: f.error ? f.error : `${plural(f.resources, "resource")}, ${plural(f.clients, "client record")}` }),
      ),
    );
    markPainted();
    $("tree").replaceChildren(
      el("p", { class: "muted", text: `The catalog backups in ${files.state_dir}, read-only, re-read when they change.` }),
      el("table", { class: "files" }, el("tr", {}, el("th", { text: "registrar" }), el("th", { text: "file" }), el("th", { text: "" }), el("th", { text: "" })), ...rows),
    );
  }

  // -- catalogs ------------------------------------------------------------------------
  // The managers' names in the tree's start order (name -> index), kept per tree object.
  const startOrders = new WeakMap();
  function startOrder(tree) {
    if (!tree) return new Map();
    let order = startOrders.get(tree);
    if (order === undefined) {
      order = new Map();
      const walk = (node) => {
        for (const child of node.children || []) {
          if (child.kind === "manager") order.set(child.name, order.size);
          else walk(child);
        }
      };
      walk(tree);
      startOrders.set(tree, order);
    }
    return order;
  }
  function sortByTree(names, tree) {
    const order = startOrder(tree);
    const at = (name) => (order.has(name) ? order.get(name) : 1e9);
    return names.sort((a, b) => at(a) - at(b) || a.localeCompare(b));
  }
  function catalogOrder() {
    const names = Object.keys(state.sections)
      .filter((k) => k.startsWith("catalog/"))
      .map((k) => k.slice(8));
    return sortByTree(names, state.sections.tree);
  }

  // A card is made again only when its section changed (or what it shows beside: buttons,
  // pages); the first `state.cards` are drawn, then a button for more.
  const cardCache = new Map(); // registrar -> {section, context, card}
  let cardsContext = 0; // bumped when every card must be made again (a page of resources)
  function cachedCard(section, member) {
    const key = `${member || ""}\u0000${section.registrar}`;
    const context = `${cardsContext}:${canFault(member)}:${state.hello.mode}:${member ? (hostOf(member) || {}).state : ""}`;
    const cached = cardCache.get(key);
    if (cached && cached.section === section && cached.context === context) return cached.card;
    const card = catalogCard(section, member);
    cardCache.set(key, { section, context, card });
    return card;
  }
  function moreCards(total) {
    if (total <= state.cards) return null;
    return el("button", {
      class: "more",
      "data-more-cards": "yes",
      text: `show ${Math.min(CARDS_PAGE, total - state.cards)} more catalogs (${state.cards} of ${total} shown)`,
      onclick: () => {
        state.cards += CARDS_PAGE;
        schedule("catalogs");
      },
    });
  }

  function renderCatalogs() {
    if (system()) return renderHostCatalogs();
    const names = catalogOrder();
    const cards = names.slice(0, state.cards).map((name) => cachedCard(state.sections[`catalog/${name}`], null));
    if (cards.length) $("catalogs").replaceChildren(...cards, ...[moreCards(names.length)].filter(Boolean));
    else renderPlaceholders();
  }

  function renderHostCatalogs() {
    const parts = [];
    for (const h of hostsList()) {
      const prefix = `host/${h.member}/catalog/`;
      const tree = state.sections[`host/${h.member}/tree`];
      const names = sortByTree(Object.keys(state.sections).filter((k) => k.startsWith(prefix)).map((k) => k.slice(prefix.length)), tree);
      const cards = names.map((name) => cachedCard(state.sections[prefix + name], h.member));
      parts.push(el("div", { class: "host-catalogs", "data-member": h.member, "data-state": h.state },
        el("h3", { class: "host-heading" }, el("span", { class: "member", text: h.member }), " ",
          el("small", { text: h.state === "live" ? plural(cards.length, "registrar") : `${h.state}: last known` })),
        ...cards));
    }
    $("catalogs").replaceChildren(...(parts.length ? parts : [el("p", { class: "muted", text: "No registrar yet." })]));
  }

  function renderPlaceholders() {
    if (!Object.keys(state.sections).some((k) => k.startsWith("catalog/")))
      $("catalogs").replaceChildren(el("p", { class: "muted", text: "No registrar yet." }));
  }

  function catalogCard(section, member) {
    const catalog = section.catalog;
    const host = member ? hostOf(member) : null;
    const stale = !section.available || Boolean(host && host.state !== "live");
    const card = el(
      "article",
      { class: `catalog${stale ? " stale" : ""}`, "data-registrar": section.registrar, "data-member": member || undefined },
      el("h3", {}, `${section.registrar} `, el("small", { text: `${section.kind} · ${section.state}${stale && catalog ? " · last seen" : ""}` })),
    );
    if (section.error) card.append(el("div", { class: "error", text: section.error }));
    if (!catalog) {
      card.append(el("div", { class: "muted", text: "catalog not known" }));
      return card;
    }
    const deps = new Map();
    const top = [];
    for (const client of catalog.clients) {
      if (client.parent) {
        if (!deps.has(client.parent)) deps.set(client.parent, []);
        deps.get(client.parent).push(client);
      } else top.push(client);
    }
    for (const server of catalog.servers) {
      const resources = catalog.resources.filter((r) => r.server === server);
      const pageKey = `${section.registrar}/${server}`;
      const shown = Math.min(resources.length, state.shown[pageKey] || PAGE);
      const list = el("ul", {}, ...resources.slice(0, shown).map((r) => resourceItem(section, r, deps.get(r.id) || [], member)));
      const more =
        shown < resources.length
          ? el("button", {
              class: "more",
              "data-more": server,
              text: `show ${Math.min(PAGE, resources.length - shown)} more (${shown} of ${resources.length} shown)`,
              onclick: () => {
                state.shown[pageKey] = shown + PAGE;
                cardsContext += 1;
                schedule("catalogs");
              },
            })
          : null;
      card.append(
        el("div", { class: "server", "data-server": server },
          el("h4", { text: `server ${server} · ${plural(resources.length, "resource")}` }),
          resources.length ? list : null, more),
      );
    }
    if (top.length) {
      card.append(
        el("h4", { text: "queries held elsewhere" }),
        el("ul", {}, ...top.map((c) => el("li", { class: "client", "data-query": c.query_id },
          el("code", { text: c.query_id.slice(0, 8) }), ` → ${c.serving_rr}/${c.server} `, el("code", { text: c.request }),
          c.loaded ? "" : " (in flight)"))),
      );
    }
    if (catalog.in_doubt && catalog.in_doubt.length) {
      card.append(
        el("h4", { text: "in doubt (a crash cut these loads short; found at restore)" }),
        el("ul", {}, ...catalog.in_doubt.map((q) => el("li", { class: "error" }, el("code", { text: q.id.slice(0, 8) }), " ", el("code", { text: q.request })))),
      );
    }
    return card;
  }

  function resourceItem(section, resource, deps, member) {
    const fatal =
      canFault(member) && state.hello.mode !== "replay" && section.available && section.kind.endsWith("manager") && resource.consumers.length
        ? el("button", {
            class: "danger",
            "data-fault": "fatal",
            text: "FATAL",
            title: "send FATAL to every consumer of this resource",
            onclick: () =>
              confirmThen(
                `Send FATAL on ${section.registrar}/${resource.server} ${resource.request}?`,
                `Every one of its ${resource.consumers.length} consumer(s) hears it, and so does every resource that depends on it, up to the top.`,
                "Send FATAL",
                () => fault("fatal", member ? { registrar: section.registrar, resource_id: resource.id, host: member } : { registrar: section.registrar, resource_id: resource.id }),
              ),
          })
        : null;
    return el(
      "li",
      { class: `resource${resource.in_doubt ? " in-doubt" : ""}`, "data-resource": resource.id },
      el("span", { class: "line" },
        el("code", { text: resource.request }), " = ", el("code", { text: resource.response }), " ",
        el("span", { class: `badge state-${resource.state}`, text: resource.in_doubt && section.kind === "backup" ? `in doubt: ${resource.state}` : resource.state }),
        ` ${plural(resource.consumers.length, "consumer")} `, fatal),
      el("ul", { class: "sub" },
        ...resource.consumers.map((c) => el("li", {}, "consumer ", el("code", { text: c.query_id.slice(0, 8) }), ` from ${c.origin}`)),
        ...deps.map((d) => el("li", {}, "depends on ", `${d.serving_rr}/${d.server} `, el("code", { text: d.request }), " via ", el("code", { text: d.query_id.slice(0, 8) }), d.loaded ? "" : " (in flight)"))),
    );
  }

  // -- the dependency graph ------------------------------------------------------------
  let cy = null;
  let graphKey = "";

  function ranks(graph) {
    const owner = {};
    for (const n of graph.nodes) owner[n.id] = n.parent || n.id;
    const above = {};
    for (const n of graph.nodes) if (n.kind === "registrar") above[n.id] = new Set();
    for (const e of graph.edges) {
      const c = owner[e.source];
      const p = owner[e.target];
      if (c && p && c !== p && above[p]) above[p].add(c);
    }
    const rank = {};
    const visit = (id, path) => {
      if (rank[id] !== undefined) return rank[id];
      let best = -1;
      for (const c of above[id] || []) if (!path.has(c)) best = Math.max(best, visit(c, new Set([...path, id])));
      rank[id] = best + 1;
      return rank[id];
    };
    for (const id of Object.keys(above)) visit(id, new Set());
    return rank;
  }

  function layout(graph) {
    const rank = ranks(graph);
    const children = {};
    for (const n of graph.nodes) if (n.parent) (children[n.parent] = children[n.parent] || []).push(n);
    const rows = {};
    for (const n of graph.nodes) if (n.kind === "registrar") (rows[rank[n.id]] = rows[rank[n.id]] || []).push(n);
    const positions = {};
    const W = 200;
    const H = 160;
    const GAP = 70;
    let widest = 0;
    const widths = {};
    for (const [r, regs] of Object.entries(rows)) {
      widths[r] = regs.reduce((sum, reg) => sum + Math.max(1, (children[reg.id] || []).length) * W + GAP, 0);
      widest = Math.max(widest, widths[r]);
    }
    for (const [r, regs] of Object.entries(rows)) {
      let x = (widest - widths[r]) / 2;
      for (const reg of regs) {
        const kids = children[reg.id] || [];
        if (!kids.length) positions[reg.id] = { x: x + W / 2, y: Number(r) * H };
        kids.forEach((kid, i) => (positions[kid.id] = { x: x + W / 2 + i * W, y: Number(r) * H }));
        x += Math.max(1, kids.length) * W + GAP;
      }
    }
    return positions;
  }

  // A graph of more than GRAPH_MAX resources: its registrars, one arrow per pair with a count.
  function summarised(graph) {
    const owner = {};
    for (const n of graph.nodes) owner[n.id] = n.parent || n.id;
    const nodes = graph.nodes.filter((n) => n.kind === "registrar").map((n) => ({ ...n }));
    const resources = {};
    for (const n of graph.nodes) if (n.parent) resources[n.parent] = (resources[n.parent] || 0) + 1;
    for (const n of nodes) if (resources[n.id]) n.label = `${n.label}\n${plural(resources[n.id], "resource")}`;
    const pairs = new Map();
    for (const e of graph.edges) {
      const key = `${owner[e.source]}>${owner[e.target]}`;
      const pair = pairs.get(key) || { id: `sum:${key}`, source: owner[e.source], target: owner[e.target], count: 0, loaded: true, orphan: false };
      pair.count += 1;
      pair.loaded = pair.loaded && e.loaded;
      pair.orphan = pair.orphan || e.orphan;
      pairs.set(key, pair);
    }
    const edges = [...pairs.values()].map((p) => ({ ...p, label: plural(p.count, "query") }));
    return { nodes, edges };
  }

  function renderGraph() {
    let graph = state.sections.graph;
    if (!graph || typeof cytoscape !== "function") return;
    const key = JSON.stringify(graph) + JSON.stringify(hostsList().map((h) => h.state));
    if (key === graphKey) return;
    graphKey = key;
    const many = graph.nodes.length - graph.nodes.filter((n) => n.kind === "registrar").length;
    let note = many > GRAPH_MAX ? `${many} resources: registrars only, arrows counted (the catalogs list them)` : "";
    if (many > GRAPH_MAX) graph = summarised(graph);
    const registrars = graph.nodes.filter((n) => n.kind === "registrar");
    if (registrars.length > GRAPH_REGISTRARS) {
      // (a row of a thousand idle registrars says nothing: those that hold or serve are drawn)
      const owner = {};
      const used = new Set();
      for (const n of graph.nodes) owner[n.id] = n.parent || n.id;
      for (const n of graph.nodes) if (n.parent) used.add(n.parent);
      for (const e of graph.edges) used.add(owner[e.source]).add(owner[e.target]);
      const idle = registrars.filter((n) => !used.has(n.id)).length;
      graph = { ...graph, nodes: graph.nodes.filter((n) => n.kind !== "registrar" || used.has(n.id)) };
      note = `${note}${note ? "; " : ""}${plural(idle, "registrar")} without resources or queries not drawn`;
    }
    $("graph-note").textContent = note;
    const elements = [
      ...graph.nodes.map((n) => ({
        data: {
          id: n.id,
          parent: n.parent,
          label: n.kind === "registrar" ? (n.host ? `${n.label} · ${n.host}` : n.label) : `${cut(n.label, 72)}${n.consumers > 1 ? ` ×${n.consumers}` : ""}`,
          kind: n.kind,
          state: n.state || "",
          host: n.host || "",
          stale: n.host && hostOf(n.host) && hostOf(n.host).state !== "live" ? "yes" : "no",
          doubt: n.in_doubt ? "yes" : "no",
        },
      })),
      ...graph.edges.map((e) => ({
        data: {
          id: e.id,
          source: e.source,
          target: e.target,
          label: e.label, // (no query ids: crossing edges' ids overlapped; "no client record" for an orphan)
          loaded: e.loaded ? "yes" : "no",
          orphan: e.orphan ? "yes" : "no",
          crosses: e.crosses ? "yes" : "no",
        },
      })),
    ];
    if (!cy) {
      cy = cytoscape({
        container: $("graph"),
        elements: [],
        minZoom: 0.2,
        maxZoom: 1.3, // (a fit of a small graph would blow it up)
        style: [
          { selector: "node", style: { label: "data(label)", "font-size": 10, "text-wrap": "wrap", "text-max-width": 160, "text-overflow-wrap": "anywhere", "text-valign": "center", "background-color": "#dcf3e5", "border-width": 1, "border-color": "#1f8a4c", shape: "round-rectangle", width: 170, height: 56 } },
          { selector: 'node[kind = "registrar"]', style: { "background-color": "#eef1f6", "border-color": "#667085", "font-weight": "bold", "text-valign": "top", "text-halign": "center", "font-size": 12 } },
          { selector: 'node[kind = "registrar"]:childless', style: { "text-valign": "center", width: 120, height: 36 } },
          { selector: "$node > node", style: { "padding-top": 22, "padding-left": 10, "padding-right": 10, "padding-bottom": 10 } },
          { selector: 'node[kind = "registrar"][state = "restarting"], node[kind = "registrar"][state = "starting"]', style: { "border-style": "dashed", "border-color": "#b7791f", "background-color": "#fff8e6" } },
          { selector: 'node[kind = "registrar"][state = "stopped"], node[kind = "registrar"][state = "exited"], node[kind = "registrar"][state = "external"]', style: { "border-style": "dotted", opacity: 0.6 } },
          { selector: 'node[state = "loading"], node[state = "unloading"]', style: { "background-color": "#fdf0d2", "border-color": "#b7791f" } },
          { selector: 'node[doubt = "yes"]', style: { "border-color": "#c53030", "border-width": 3 } },
          { selector: "node.fatal", style: { "background-color": "#c53030", color: "#fff" } },
          { selector: "edge", style: { width: 1.5, "curve-style": "bezier", "target-arrow-shape": "triangle", "line-color": "#7c8aa5", "target-arrow-color": "#7c8aa5", label: "data(label)", "font-size": 9, "text-background-color": "#fbfcfd", "text-background-opacity": 1 } },
          { selector: 'edge[loaded = "no"]', style: { "line-style": "dashed" } },
          { selector: 'edge[crosses = "yes"]', style: { width: 2.5, "line-color": "#6b46c1", "target-arrow-color": "#6b46c1" } },
          { selector: 'node[stale = "yes"]', style: { opacity: 0.35, "border-style": "dashed" } },
          { selector: 'edge[orphan = "yes"]', style: { "line-style": "dashed", "line-color": "#c53030", "target-arrow-color": "#c53030", color: "#c53030" } },
        ],
      });
    }
    if (!cy.scratch("taps")) {
      cy.scratch("taps", true);
      cy.on("tap", "edge", (e) => cutOnTap(e.target));
    }
    const ids = elements.map(({ data: d }) => `${d.id} ${d.parent || ""} ${d.source || ""} ${d.target || ""}`).sort().join("\n");
    if (ids === cy.scratch("ids")) {
      // the same nodes and arrows, in the same boxes (a state or a label changed): data only
      cy.batch(() => elements.forEach((e) => cy.getElementById(e.data.id).data(e.data)));
      $("graph").dataset.labels = JSON.stringify(cy.nodes('[kind = "resource"]').map((n) => n.data("label")));
      return;
    }
    cy.scratch("ids", ids);
    const positions = layout(graph);
    cy.batch(() => {
      cy.elements().remove();
      cy.add(elements);
    });
    $("graph").dataset.labels = JSON.stringify(cy.nodes('[kind = "resource"]').map((n) => n.data("label"))); // (the canvas's text, readable)
    cy.layout({ name: "preset", positions: (node) => positions[node.id()] || { x: 0, y: 0 }, fit: true, padding: 24 }).run();
  }

  function flashResourceOf(registrar, queryId, member) {
    const section = catalogSection(registrar, member);
    const catalog = section && section.catalog;
    if (!cy || !catalog) return;
    const resource = catalog.resources.find((r) => r.consumers.some((c) => c.query_id === queryId));
    if (!resource) return;
    const node = cy.getElementById(`res:${registrar}:${resource.id}`);
    node.addClass("fatal");
    setTimeout(() => node.removeClass("fatal"), 3000);
  }

  // -- events: the timeline and the log -----------------------------------------------
  function addEvent(event) {
    state.events.push(event);
    if (state.events.length > MAX_EVENTS) state.events.splice(0, state.events.length - MAX_EVENTS);
    addLog(event);
    switch (event.type) {
      case "StatusSent": {
        const row = { kind: "status", event, hops: [] };
        state.orphans = state.orphans.filter((o) => !(matches(event, o.event) && row.hops.push(o.event)));
        // deliveries drawn alone because this send came later than ORPHAN_S: its hops too
        state.rows = state.rows.filter((r) => !(r.kind === "status" && !r.event && matches(event, r.hops[0]) && row.hops.push(...r.hops)));
        pushRow(row);
        if (event.status === "FATAL" || event.status === "ERROR") flashResourceOf(event.registrar, event.query_id, event.member);
        break;
      }
      case "StatusDelivered": {
        const row = findSent(event);
        if (row) row.hops.push(event);
        else state.orphans.push({ event, arrived: Date.now() / 1000 });
        break;
      }
      case "ChildExited":
      case "ChildRestarted":
      case "SupervisorGaveUp":
      case "ManagerOverloaded":
      case "ServerOverloaded":
      case "LoadFailed":
      case "InDoubt":
        pushRow({ kind: "child", event });
        break;
      case "ObserverFault":
        pushRow({ kind: "fault", event });
        break;
      default:
        break;
    }
  }

  // A delivery can reach the page before its send (they come from different processes);
  // it waits ORPHAN_S seconds of the page's own time after it arrived, so that a page
  // opened late, which gets the whole history at once, draws it as a live page did.
  function flushOrphans() {
    const now = Date.now() / 1000;
    let flushed = false;
    state.orphans = state.orphans.filter((o) => {
      if (now - o.arrived < ORPHAN_S) return true;
      pushRow({ kind: "status", event: null, hops: [o.event] }); // its send never came (dropped?)
      flushed = true;
      return false;
    });
    if (flushed) schedule("events");
  }

  function matches(sent, delivered) {
    return sent.status === delivered.status && Math.abs(delivered.at - delivered.latency_s - sent.at) < MATCH_S;
  }

  function findSent(delivered) {
    for (let i = state.rows.length - 1; i >= 0; i--) {
      const row = state.rows[i];
      if (row.kind === "status" && row.event && matches(row.event, delivered)) return row;
    }
    return null;
  }

  function pushRow(row) {
    state.rows.push(row);
    if (state.rows.length > MAX_ROWS) state.rows.splice(0, state.rows.length - MAX_ROWS);
  }

  function addLog(event) {
    state.log.push(event);
    if (state.log.length > MAX_LOG) state.log.splice(0, state.log.length - MAX_LOG);
  }

  // A status row names its resource as the graph does (its label, not its request): as the
  // server named it when it was sent (it may be unloaded since: LiDAR 1 after F1), else now.
  // The observer names every one as it enters its history (StatusNames: LiveSource for its
  // own tree, SystemView for the system's event stream): a page open during the send and one
  // opened later draw the same row. "Now" is for an event no server named (a host's older
  // observer).
  function resourceName(sent) {
    if (sent.resource) return sent.resource;
    const section = catalogSection(sent.registrar, sent.member);
    const catalog = section && section.catalog;
    const resource = catalog && catalog.resources.find((r) => r.consumers.some((c) => c.query_id === sent.query_id));
    return resource ? `${sent.registrar}/${resource.server} ${resource.label || resource.request}` : `${sent.registrar} (query ${sent.query_id.slice(0, 8)})`;
  }

  function renderTimeline() {
    if (state.hello.mode === "backups") {
      $("timeline").replaceChildren(el("li", { class: "muted", text: "No live events: this page reads backups." }));
      return;
    }
    const items = [];
    for (let i = state.rows.length - 1; i >= 0; i--) items.push(timelineItem(state.rows[i]));
    if (!items.length) items.push(el("li", { class: "muted", text: "No status sent yet." }));
    $("timeline").replaceChildren(...items);
  }

  function timelineItem(row) {
    if (row.kind === "status") {
      const sent = row.event;
      const first = sent || row.hops[0];
      const hops = [...row.hops].sort((a, b) => a.hop - b.hop || a.latency_s - b.latency_s);
      return el(
        "li",
        { class: `status status-${first.status}`, "data-kind": "status", "data-status": first.status },
        timeEl(sent ? sent.at : first.at - first.latency_s),
        el("span", { class: `badge status-${first.status}`, text: first.status }),
        " ",
        sent ? `${resourceName(sent)}: ${sent.message}` : "(its send was not seen)",
        el("ol", { class: "hops" },
          ...hops.map((d) => el("li", { "data-hop": d.hop }, `hop ${d.hop} → ${d.registrar} (query ${d.query_id.slice(0, 8)}) after ${ms(d.latency_s)}`)),
          hops.length ? null : el("li", { text: "no consumer heard it yet" })),
      );
    }
    const event = row.event;
    return el(
      "li",
      { class: row.kind, "data-kind": row.kind, "data-type": event.type },
      timeEl(event.at),
      event.text,
    );
  }

  function timeEl(at) {
    const t = since(at);
    return el("time", { text: clock(at), title: t ? `${t} (${state.sections.clock.label})` : null },
      t ? el("span", { class: "since", text: ` ${t}` }) : null);
  }

  function renderLog() {
    const items = [];
    for (let i = state.log.length - 1; i >= 0; i--) {
      const event = state.log[i];
      items.push(el("li", { "data-type": event.type || "", "data-member": event.member || undefined }, timeEl(event.at),
        event.member ? el("span", { class: "badge member-badge", text: event.member }) : null, event.member ? " " : null, event.text));
    }
    $("log").replaceChildren(...items);
    $("log-note").textContent = `the last ${Math.min(state.log.length, MAX_LOG)}, newest first`;
  }

  // -- a replay: one step at a time, asked of the server --------------------------------
  const PLAY_EVERY = 400; // ms between two steps while playing
  const replay = { asked: null, playing: null };

  async function goTo(step) {
    const section = state.sections.replay;
    if (!section) return;
    const target = Math.max(1, Math.min(section.steps, step));
    replay.asked = target;
    $("replay-panel").dataset.asked = target;
    try {
      const response = await fetch("/api/control", {
        method: "POST",
        headers: { "Content-Type": "application/json", "X-RR-Token": token },
        body: JSON.stringify({ step: target }),
      });
      const answer = await response.json();
      if (!answer.ok) notice(answer.message, true);
    } catch (error) {
      notice(`the request failed: ${error}`, true);
    }
  }
  // (the step last asked for: clicks faster than the stream count from it)
  // A live replay (hello.branches): a kill or a cut runs the seed again with that fault
  async function branch(kind, target) {
    pause();
    try {
      const response = await fetch("/api/control", {
        method: "POST",
        headers: { "Content-Type": "application/json", "X-RR-Token": token },
        body: JSON.stringify({ fault: kind, target }),
      });
      const answer = await response.json();
      replay.asked = null;
      notice(answer.message, !answer.ok);
    } catch (error) {
      notice(`the request failed: ${error}`, true);
    }
  }
  function managerOf(nodeId) {
    const name = nodeId.startsWith("res:") ? nodeId.split(":")[1] : nodeId.replace(/^reg:/, "");
    const find = (node) => (node.name === name && node.kind === "manager" ? node : (node.children || []).map(find).find(Boolean));
    return state.sections.tree ? find(state.sections.tree) : null;
  }
  function cutOnTap(edge) {
    const manager = managerOf(edge.data("target"));
    if (!canFault(null) || !manager || manager.isolation !== "process") return;
    confirmThen(`Cut ${manager.name}'s links after this step?`,
      "The seed runs again with that cut (cut_connections after this step's event): every link to it closes.",
      "cut", () => branch("cut", manager.name));
  }
  const shownStep = () => (replay.asked !== null ? replay.asked : state.sections.replay ? state.sections.replay.step : 1);

  function pause() {
    clearInterval(replay.playing);
    replay.playing = null;
    $("replay-play").textContent = "\u25B6 play";
    $("replay-panel").dataset.playing = "";
  }
  function play() {
    if (replay.playing !== null) return pause();
    $("replay-play").textContent = "\u23F8 pause";
    $("replay-panel").dataset.playing = "1";
    replay.playing = setInterval(() => {
      const section = state.sections.replay;
      if (!section || section.step >= section.steps) return pause();
      if (replay.asked !== null && replay.asked > section.step) return; // (the last ask not shown yet)
      goTo(section.step + 1);
    }, PLAY_EVERY);
  }

  function renderReplay() {
    const section = state.sections.replay;
    if (!section) return;
    const panel = $("replay-panel");
    panel.dataset.step = section.step;
    const scrub = $("replay-scrub");
    scrub.max = section.steps;
    if (document.activeElement !== scrub) scrub.value = section.step;
    $("replay-where").textContent = `step ${section.step} of ${section.steps} · ${section.at_s.toFixed(3)} s · seed ${section.seed}`;
    renderVerdict(section.check);
    $("replay-story").replaceChildren(...section.story.map((row) => {
      const where = row.step === section.step ? "current" : row.step > section.step ? "future" : "past";
      const stamp = row.who === "violation" ? "^" : `[${row.at_s.toFixed(3)} s] #${row.line}`;
      return el("li", {
        class: `${where}${row.marked ? " marked" : ""}${row.violating ? " violating" : ""}`, "data-step": row.step, "data-who": row.who,
        onclick: () => { pause(); goTo(row.step); },
      }, `${row.step}. ${stamp} ${row.who === "violation" ? "" : row.who}  ${row.text}`);
    }));
    const flight = section.in_flight.map((row) =>
      el("li", { "data-kind": row.kind, "data-id": row.id },
        el("span", { class: "badge", text: row.kind }), " ", `${row.from} → ${row.to} `,
        el("code", { text: row.id.slice(0, 8) }), ` (${row.then})`));
    $("replay-flight").replaceChildren(...(flight.length ? flight : [el("li", { class: "muted", text: "nothing in flight" })]));
  }

  // The check's verdict of the run: the exercise's rules too, not the checker's alone
  function renderVerdict(check) {
    const box = $("replay-verdict");
    box.dataset.outcome = check.outcome;
    const passed = check.outcome === "passed";
    $("replay-outcome").textContent = passed ? "passed" : "FAILED";
    $("replay-rule").textContent = check.rule ? `[${check.rule}]` : "";
    $("replay-message").textContent = check.message
      + (check.checker !== "held" || passed ? "" : " (the semantic rules' checker alone: held; the exercise's own rule broke)");
    $("replay-words").textContent = passed ? check.words || "every rule held" : check.words ? `the rule: ${check.words}` : "";
    const button = $("replay-violation");
    button.hidden = check.step === null;
    button.dataset.step = check.step === null ? "" : check.step;
    button.textContent = check.step === null ? "" : `first violating step: ${check.step}`;
  }
  $("replay-violation").addEventListener("click", (e) => { pause(); goTo(Number(e.target.dataset.step)); });
  $("replay-first").addEventListener("click", () => { pause(); goTo(1); });
  $("replay-back").addEventListener("click", () => { pause(); goTo(shownStep() - 1); });
  $("replay-step").addEventListener("click", () => { pause(); goTo(shownStep() + 1); });
  $("replay-play").addEventListener("click", play);
  $("replay-scrub").addEventListener("input", (e) => { pause(); goTo(Number(e.target.value)); });
  document.addEventListener("keydown", (e) => {
    if (!state.hello || state.hello.mode !== "replay" || e.target.tagName === "INPUT") return;
    if (e.key === "ArrowRight") { pause(); goTo(shownStep() + 1); }
    else if (e.key === "ArrowLeft") { pause(); goTo(shownStep() - 1); }
    else if (e.key === "Home") { pause(); goTo(1); }
    else if (e.key === " ") { e.preventDefault(); play(); }
  });

  // -- start ---------------------------------------------------------------------------
  setInterval(() => {
    tickCountdowns();
    if (state.hello && !state.sections.ended && state.sections.clock) renderClock();
  }, 100);
  setInterval(flushOrphans, 500);
  connect();
})();
