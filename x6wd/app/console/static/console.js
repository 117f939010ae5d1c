// x6wd operator console (docs/console.md). Plain JS, no build step, nothing from elsewhere:
// it works offline. One WebSocket to the daemon carries the control protocol
// (docs/protocol.md) and the live events.
"use strict";

(function () {
  const R_EARTH_M = 6371008.8; // mean radius: the map's equirectangular local frame
  // An authenticated page hears from the daemon every second at least (its status poll): this
  // long without a word, the link is taken for dead (a frozen daemon or a silent network),
  // the values shown are marked stale and the page connects again.
  const SILENCE_MS = 3000;
  const $ = (id) => document.getElementById(id);
  const S = {
    ws: null, nextId: 1, pending: new Map(), info: null, authed: false,
    tel: null, devices: null, links: null, sky: null,
    origin: null, // [lat, lon] of the map's local frame: the geofence centre, else the first fix
    map: { revision: -1, waypoints: [], launch: null, geofence: null },
    draft: [], dirty: false, adding: false,
    // the robot's mission changed under an unsent draft (another page or client loaded one):
    // the next Send says so and only the one after it replaces that mission
    sending: 0, draftStale: false, replaceAsked: false, ownRevisions: new Set(),
    track: [], trackEpoch: 0, view: { e: 0, n: 0, pxPerM: 4 }, followed: false,
    missionVersion: 0, draws: 0, layerDraws: 0, drawMs: 0, // the map's redraws (for the tests)
    drive: null, driveKey: null, driveTimer: null, press: null, driveSend: null, tiles: new Map(),
    pressState: null, // the press held now: { ok: a drive of it was obeyed, inflight, stopOnOk }
    driver: null, // who else drives (status' manual_drive.owner, or a "busy" refusal's driver)
    heardAt: 0, stale: true, closedWhy: "", // closedWhy: the console's reason for closing the link (full)
    held: [], // requests too large to send before auth: { id, text, resolve }, sent once it succeeds
  };
  window.x6wd = S; // for a person at the browser's console, and for the tests

  // -- geometry: local east/north metres around S.origin ------------------------------------
  // longitudes the short way round: a robot across the 180th meridian from the origin is
  // metres east or west of it, not the Earth's circumference
  function wrapDeg(d) { return d > 180 ? d - 360 : d <= -180 ? d + 360 : d; }
  function toLocal(lat, lon) {
    const [lat0, lon0] = S.origin;
    const k = Math.PI / 180 * R_EARTH_M;
    return [wrapDeg(lon - lon0) * k * Math.cos(lat0 * Math.PI / 180), (lat - lat0) * k];
  }
  function toLatLon(e, n) {
    const [lat0, lon0] = S.origin;
    const k = Math.PI / 180 * R_EARTH_M;
    return [lat0 + n / k, wrapDeg(lon0 + e / (k * Math.cos(lat0 * Math.PI / 180)))];
  }
  S.geo = { toLocal, toLatLon }; // the map's frame, for the tests
  const canvas = $("map");
  const ctx = canvas.getContext("2d");
  S.canvas = canvas;
  function toScreen(e, n) {
    const v = S.view;
    return [canvas.clientWidth / 2 + (e - v.e) * v.pxPerM, canvas.clientHeight / 2 - (n - v.n) * v.pxPerM];
  }
  function fromScreen(x, y) {
    const v = S.view;
    return [v.e + (x - canvas.clientWidth / 2) / v.pxPerM, v.n - (y - canvas.clientHeight / 2) / v.pxPerM];
  }
  S.toScreen = (lat, lon) => toScreen(...toLocal(lat, lon)); // canvas pixels of a position
  const wrap360 = (deg) => ((deg % 360) + 360) % 360; // the one heading convention
  const fmt = (v, d) => (v === null || v === undefined ? "—" : Number(v).toFixed(d));

  // -- messages ----------------------------------------------------------------------------
  function say(text, isError) {
    const m = $("msg");
    m.textContent = text;
    m.className = isError ? "err" : "";
  }
  // the text's UTF-8 size (bytes) is over limit (the length is a bound: 3 bytes a char at most)
  const over = (text, limit) => text.length > limit / 3 && new TextEncoder().encode(text).length > limit;
  // Until its auth succeeds the console closes a page that sends a message over
  // max_message_bytes_before_auth (1009). A larger request made meanwhile (Send mission
  // clicked while a reconnected page's automatic auth is in flight) is held and sent once
  // the auth succeeds; so is every request after it, to keep their order. A stop is never held.
  const preAuthLimit = () => (S.info && S.info.max_message_bytes_before_auth) || 4096;
  function request(cmd, args) {
    return new Promise((resolve) => {
      if (!S.ws || S.ws.readyState !== WebSocket.OPEN) {
        resolve({ ok: false, error: { code: "closed", message: "not connected" + (S.closedWhy ? " (" + S.closedWhy + ")" : "") } });
        return;
      }
      const id = S.nextId++;
      // sent_ms: the console refuses a drive that arrives later than it would have lasted
      // (one held in a stalled link's buffers must not move the robot when the link thaws);
      // a held request keeps it (when it was asked for: another client's stop since refuses it)
      const sent = Math.round(performance.now());
      const text = JSON.stringify(Object.assign({ id: id, cmd: cmd, sent_ms: sent }, args || {}));
      // the console closes the link on a message over its limit: refused here instead
      const limit = S.info ? S.info.max_message_bytes : Infinity;
      if (over(text, limit)) {
        resolve({ ok: false, error: { code: "too_large", message: "too large to send: the console takes at most " + limit + " bytes (console.max_message_bytes)" } });
        return;
      }
      if (!S.authed && cmd !== "stop") {
        const early = preAuthLimit();
        if (cmd === "auth" && over(text, early)) { // it would never succeed: nothing to wait for
          resolve({ ok: false, error: { code: "too_large", message: "the token is too long: at most " + early + " bytes before auth" } });
          return;
        }
        if (cmd !== "auth" && (S.held.length || over(text, early))) {
          S.held.push({ id: id, text: text, resolve: resolve });
          say(cmd + ": waiting for the token to be accepted before sending");
          return;
        }
      }
      S.pending.set(id, resolve);
      S.ws.send(text);
    });
  }
  // the held requests: sent (the auth succeeded on this link) or refused with why
  function releaseHeld(why) {
    const held = S.held;
    S.held = [];
    for (const h of held) {
      if (why) h.resolve({ ok: false, error: { code: "not_sent", message: "not sent: " + why } });
      else { S.pending.set(h.id, h.resolve); S.ws.send(h.text); }
    }
  }
  function report(cmd, r) {
    if (r.ok) say(cmd + ": ok" + (r.state ? " (" + r.mode + " " + r.state + ")" : ""));
    else say(cmd + ": " + r.error.message, true);
    return r;
  }
  async function command(cmd, args) {
    return report(cmd, await request(cmd, args));
  }
  // The stop: its message leaves first (request() sends before it returns), then the page's
  // own drive ends and the answer is shown when it comes.
  function stopNow() {
    const answer = request("stop");
    // nothing asked for before the stop runs after it (a held start, say)
    if (S.held.length) releaseHeld("a stop came before the token was accepted");
    endDrive(false);
    answer.then((r) => report("stop", r));
  }

  // -- the connection ------------------------------------------------------------------------
  function connect() {
    const ws = new WebSocket((location.protocol === "https:" ? "wss://" : "ws://") + location.host + "/ws");
    S.ws = ws;
    S.heardAt = performance.now();
    ws.onmessage = (ev) => {
      if (S.ws !== ws) return; // a link given up for dead that woke up: not listened to
      S.heardAt = performance.now();
      onMessage(JSON.parse(ev.data));
    };
    ws.onopen = () => { S.closedWhy = ""; };
    ws.onclose = (ev) => {
      if (S.ws !== ws) return;
      // 1013 "try again later": the console is full (its reason says so), or closed this
      // page to make room for another; any other close with a reason (1009: a message too
      // big) says it too, in the status and the message line (the status changes on reconnecting)
      S.closedWhy = ev.code === 1013 ? ev.reason || "console full" : ev.reason || (ev.code === 1009 ? "message too big" : "");
      linkLost(ev.code === 1013 ? S.closedWhy : S.closedWhy ? "disconnected: " + S.closedWhy : "disconnected");
      if (S.closedWhy) say("the console closed the connection: " + S.closedWhy + " (code " + ev.code + ")", true);
      setTimeout(connect, 1000);
    };
  }
  // the link is gone (closed, or silent too long): nothing shown is live any more
  function linkLost(why) {
    endDrive(false);
    S.authed = false;
    const lost = "connection lost" + (S.closedWhy ? " (" + S.closedWhy + ")" : "");
    releaseHeld(lost + " before the token was accepted");
    for (const resolve of S.pending.values()) resolve({ ok: false, error: { code: "closed", message: lost } });
    S.pending.clear();
    setConn(why, "bad");
    setStale(true);
  }
  function setStale(stale) {
    if (stale !== S.stale) redraw(); // the robot drawn grey, or green again
    S.stale = stale;
    document.body.classList.toggle("stale", stale);
  }
  // a closed link says so at once; a silent one (a frozen daemon, a dead network path: no
  // FIN, no close for a long while) only by its silence
  setInterval(() => {
    const ws = S.ws;
    if (!ws || !S.authed || performance.now() - S.heardAt < SILENCE_MS) return;
    S.ws = null; // its late messages and its close are ignored from here on
    linkLost("no data for " + Math.round(SILENCE_MS / 1000) + " s: reconnecting");
    ws.close();
    connect();
  }, 250);
  function setConn(text, cls) {
    const c = $("conn");
    c.textContent = text;
    c.className = "pill " + cls;
  }
  function onMessage(m) {
    if (m.id !== undefined && m.id !== null && S.pending.has(m.id)) {
      const resolve = S.pending.get(m.id);
      S.pending.delete(m.id);
      resolve(m);
      return;
    }
    if (m.event === "console") return onWelcome(m);
    if (m.event === "telemetry") return onTelemetry(m.data, m.devices);
    if (m.event === "state") return onState(m);
    if (m.event === "sky") { S.sky = m; return renderSky(); }
    if (m.event === "map") return onMap(m);
    if (m.event === "track") return onTrack(m.points);
    if (m.ok === false && m.error) say(m.error.message, true); // e.g. the closing notice
  }
  function onState(m) {
    say("state " + m.old + " → " + m.new + " (" + m.reason + ")");
    // a mode change: why the robot paused (the operator, a failsafe), for showWhy
    const why = String(m.reason || "");
    if (why.startsWith("mode: ")) S.pauseWhy = m.new === "PAUSED" ? why.slice(6) : "";
    // the held drive's MANUAL ended (a stop, maybe another client's): its resend goes now,
    // and the daemon says whether this press may still drive (a stop from elsewhere after
    // the press began: refused, reason "stopped", which ends the press below)
    if (m.old === "MANUAL" && S.driveSend) S.driveSend();
  }
  function onWelcome(m) {
    S.info = m;
    // a new connection may be to a new daemon, whose revisions count from 0 again: its map
    // is taken whatever its revision (else the old mission stayed, and "Send" put it back)
    S.map.revision = -1;
    S.pauseWhy = ""; // what happened while the page was away is not known
    document.body.classList.toggle("watch-only", m.watch_only);
    redraw(); // the tiles (tile_url)
    $("watch-only").hidden = !m.watch_only;
    $("deadman-note").textContent = "Dead-man: each drive lasts " + m.deadman_s + " s and is repeated while you hold; " +
      "letting go, hiding or closing this page, or losing the link stops the motors.";
    if (!m.auth_required) return authenticated();
    const token = sessionStorage.getItem("x6wd-token");
    if (token) auth(token); else showLogin("");
  }
  async function auth(token) {
    const r = await request("auth", { token: token });
    if (r.ok) {
      sessionStorage.setItem("x6wd-token", token);
      $("login").hidden = true;
      authenticated();
    } else {
      sessionStorage.removeItem("x6wd-token");
      releaseHeld("the token was refused (" + r.error.message + ")");
      showLogin(r.error.message);
    }
  }
  function showLogin(error) {
    setConn("token needed", "warn");
    $("login").hidden = false;
    $("login-error").textContent = error;
    $("token-input").focus();
  }
  function authenticated() {
    S.authed = true;
    setConn("connected" + (S.info.tls ? " (TLS)" : ""), "ok");
    releaseHeld("");
    poll(S.ws);
  }
  // status once a second: links and devices, and (for a page that may command) the
  // operator-link failsafe's sign of life
  // (one loop per link: a loop of an earlier link ends)
  async function poll(ws) {
    if (!S.authed || S.ws !== ws) return;
    const r = await request("status");
    if (S.ws !== ws) return;
    if (r.ok) {
      S.links = r.links;
      S.status = r;
      if (r.devices) S.devices = r.devices;
      // the compass heading is magnetic while the WMM declination is pending or failed
      const d = r.declination;
      S.north = d && typeof d === "object" && ("pending" in d || "error" in d) ? "magnetic" : "true";
      if ((!S.tel || S.stale) && r.telemetry) onTelemetry(r.telemetry, r.devices);
      // who drives, when it is not this page (null: nobody's drive holds)
      if ("manual_drive" in r) showDriver(r.manual_drive && !r.manual_drive.yours ? r.manual_drive.owner : null);
      renderDevices();
    }
    setTimeout(() => poll(ws), 1000);
  }

  // -- telemetry --------------------------------------------------------------------------------
  const FIX = { 0: "no fix", 1: "GPS", 2: "DGPS", 4: "RTK fixed", 5: "RTK float", 6: "dead reckoning" };
  function onTelemetry(t, devices) {
    S.tel = t;
    setStale(false);
    if (devices) S.devices = devices;
    const lat = t.filt_lat_deg !== null ? t.filt_lat_deg : t.lat_deg;
    const lon = t.filt_lon_deg !== null ? t.filt_lon_deg : t.lon_deg;
    if (lat !== null && lon !== null) {
      if (!S.origin) S.origin = [lat, lon];
      const p = toLocal(lat, lon);
      const last = S.track[S.track.length - 1];
      if (!last || Math.hypot(p[0] - last[0], p[1] - last[1]) > 0.05) {
        S.track.push(p);
        if (S.track.length > 20000) { S.track.splice(0, 5000); S.trackEpoch++; }
      }
      if ($("follow").checked) { S.view.e = p[0]; S.view.n = p[1]; }
      // the EKF's estimate stands in for a fix that is gone: said (the client's status shows
      // "position - -" and the filtered line apart)
      const estimated = t.lat_deg === null || t.lon_deg === null;
      $("tel-pos").textContent = fmt(lat, 7) + ", " + fmt(lon, 7) + (estimated ? "  (estimate: no fix)" : "");
      $("tel-local").textContent = "E " + fmt(p[0], 1) + " m  N " + fmt(p[1], 1) + " m";
    }
    $("mode").textContent = t.mode;
    $("state").textContent = t.state;
    $("mode").className = "pill live " + (t.mode === "RUNNING" || t.mode === "MANUAL" ? "ok" : t.mode === "DONE" ? "info" : "");
    $("hold").hidden = !t.hold_reason;
    $("hold").textContent = t.hold_reason || "";
    showWhy(t);
    // 99.99: a receiver's "no HDOP" (no fix), not a dilution of 100
    const hdop = t.hdop !== null && t.hdop >= 99.99 ? null : t.hdop;
    $("tel-fix").textContent = (FIX[t.fix_quality] || "quality " + t.fix_quality) + "  HDOP " + fmt(hdop, 1) + "  age " + fmt(t.fix_age_s, 1) + " s";
    $("tel-sats").textContent = t.sats_used === null ? "—" : t.sats_used + " used";
    $("tel-heading").textContent = t.heading_deg === null ? "—" : fmt(wrap360(t.heading_deg), 1) + "° " + (S.north || "true");
    $("tel-attitude").textContent = fmt(t.pitch_deg, 1) + "° / " + fmt(t.roll_deg, 1) + "°";
    let wp = "—";
    if (t.waypoint_index !== null && t.waypoint_count) {
      wp = (t.waypoint_index + 1) + " / " + t.waypoint_count + "  " + fmt(t.distance_m, 1) + " m";
      if (t.target_bearing_deg !== null) wp += "  bearing " + fmt(wrap360(t.target_bearing_deg), 0) + "°";
    }
    $("tel-wp").textContent = wp;
    $("tel-motors").textContent = "L " + fmt(t.left_pct, 0) + " %  R " + fmt(t.right_pct, 0) + " %";
    renderDevices();
    redraw();
  }
  // Why the robot is off its mission, from the telemetry's `extra` as `x6wd client status`
  // prints it: a return to launch and its cause (`returning`), and the last failsafe that acted
  // (`failsafe`, kept until the next start). Every telemetry carries them (the status poll's
  // too), so they stay while they hold and a page opened later shows them; the one-off state
  // change in the message line is overwritten by the next answer (an outside audit: after a
  // failsafe pause the page said PAUSED / IDLE and nowhere why).
  function showWhy(t) {
    const x = t.extra && typeof t.extra === "object" ? t.extra : {};
    const ret = String(x.returning || ""), fs = String(x.failsafe || "");
    const r = $("returning");
    r.hidden = !ret;
    r.textContent = ret ? "return to launch (" + (ret === "return" ? "the operator's command" : ret) + ")" : "";
    r.className = "pill live " + (ret.startsWith("failsafe") ? "bad" : "info");
    // paused by it: the telemetry says who paused (extra.paused_by), so a page opened after
    // the operator's own pause that followed a resumed failsafe does not cry failsafe; a
    // daemon without the key: the pause this page saw
    const by = x.paused_by !== undefined ? String(x.paused_by) : S.pauseWhy;
    const holds = t.mode === "PAUSED" && !(by && !by.startsWith("failsafe"));
    const f = $("failsafe");
    f.hidden = !fs || "failsafe: " + fs === ret;
    f.textContent = fs ? (holds ? "failsafe: " : "last failsafe: ") + fs : "";
    f.title = f.textContent;
    r.title = r.textContent;
    f.className = "pill live " + (holds ? "bad" : "");
  }
  function renderSky() {
    const sats = (S.sky.satellites || []).slice().sort((a, b) => (b.cn0_dbhz || 0) - (a.cn0_dbhz || 0));
    const body = $("sky").tBodies[0];
    body.textContent = "";
    for (const s of sats) {
      const tr = body.insertRow();
      const cn0 = s.cn0_dbhz;
      tr.insertCell().textContent = s.prn;
      tr.insertCell().textContent = fmt(s.el_deg, 0);
      tr.insertCell().textContent = fmt(s.az_deg, 0);
      const td = tr.insertCell();
      const bar = document.createElement("span");
      bar.className = "bar" + (s.used ? "" : " unused");
      bar.style.width = Math.max(0, Math.min(60, (cn0 || 0) - 10)) * 2 + "px";
      td.append(bar, cn0 === null ? "—" : String(Math.round(cn0)));
      tr.insertCell().textContent = s.used ? "yes" : "";
    }
    $("sky-summary").textContent = sats.length + " in view, " + sats.filter((s) => s.used).length + " used";
  }
  // One row of the devices table: the state, its count, why it is in that state now (`reason`,
  // docs/protocol.md) and, apart and marked so, an older fault (`last_error`). Before (an
  // outside audit) the detail was `last_error || reason`: a compass the EKF refused showed an
  // I2C error cleared long before, and a latched motor fault an older text with the wrong
  // action for the operator.
  function deviceRow(body, name, state, count, why, last) {
    const tr = body.insertRow();
    tr.insertCell().textContent = name;
    const st = tr.insertCell();
    st.textContent = state;
    st.className = "st-" + state.replace(/ /g, "-");
    tr.insertCell().textContent = count === undefined || count === null ? "" : count;
    const td = tr.insertCell();
    td.textContent = why || "";
    if (last && last !== why) {
      const old = document.createElement("small");
      old.className = "last-error";
      old.textContent = "last error: " + last;
      td.append(old);
    }
  }
  const SETUP_OK = ["acked", "waiting", "not sent"]; // client.py's SETUP_OK_STATES
  // The rest of `status` that `x6wd client status` prints as a problem, a row each: the motor
  // link, the recorder (always: recording is how a run is looked at afterwards), and while they
  // hold the GPS receiver's problems, corrupt GPS input, a receiver's week rollover corrected,
  // the TLS certificate's warning.
  function statusRows(body, r) {
    const links = r.links || {};
    deviceRow(body, "motor link", String(links.motors || "unknown"));
    const rec = r.recorder;
    if (rec && typeof rec === "object") {
      const bad = rec.state !== "ok";
      // stalled: a write that has not returned (no error yet), its records waiting in memory
      const why = rec.state === "stalled"
        ? "a write has taken " + Math.round(Number(rec.busy_s) || 0) + " s; " + (rec.queued || 0) + " records waiting"
        : rec.last_error || "?";
      deviceRow(body, "recorder", String(rec.state), rec.errors,
        bad ? why + " (" + (rec.records_dropped || 0) + " records not recorded)" : "",
        bad ? "" : rec.last_error);
    } else if (links.recorder) deviceRow(body, "recorder", String(links.recorder));
    const g = r.gps_receiver;
    if (g && typeof g === "object") {
      const setup = g.setup && typeof g.setup === "object" ? g.setup : {};
      const p = [];
      if (g.slow) p.push(["slow", g.slow]);
      if (g.line_full) p.push(["line full", g.line_full]);
      if (setup.line_short) p.push(["line short", setup.line_short]);
      if (g.setup && !SETUP_OK.includes(setup.state)) {
        p.push(["setup " + setup.state, setup.not_kept || setup.problem || setup.lost || ""]);
      }
      if (p.length) deviceRow(body, "gps receiver", p[0][0], undefined, p.map((x) => x[0] + ": " + x[1]).join("; "));
    }
    // every device's input counted and skipped (the gps's sentences, the compass's registers
    // that disagree or are out of range), as the client prints it
    for (const [name, dev] of Object.entries(S.devices || {})) {
      const corrupt = dev && typeof dev === "object" ? dev.corrupt : null;
      if (corrupt && typeof corrupt === "object" && Object.values(corrupt).some((n) => n)) {
        const counts = Object.entries(corrupt).filter(([, n]) => n).map(([k, n]) => n + " " + k.replace(/_/g, " "));
        deviceRow(body, name + " input", "corrupt", undefined, "since start: " + counts.join(", "));
      }
    }
    const roll = r.gps_week_rollover;
    if (roll && roll.corrected) {
      deviceRow(body, "gps date", "corrected", roll.corrected, "receiver week rollover: " + roll.receiver_utc +
        " read as " + roll.corrected_utc + " (+" + roll.weeks_added + " weeks; receiver firmware older than the rollover)");
    }
    const tls = r.server && r.server.tls;
    if (tls && tls.warning) deviceRow(body, "tls certificate", String(tls.state), undefined, tls.warning);
  }
  function renderDevices() {
    const d = S.devices;
    if (!d) return;
    const body = $("devices").tBodies[0];
    body.textContent = "";
    for (const name of Object.keys(d)) {
      const h = d[name];
      if (!h) { deviceRow(body, name, "—"); continue; }
      const count = h.errors !== undefined ? h.errors : h.failures;
      const why = h.reason || (h.readings !== undefined ? h.readings + " readings" : "");
      deviceRow(body, name, String(h.state || "?"), count, why, h.last_error);
    }
    if (S.status) statusRows(body, S.status);
    else if (S.links) deviceRow(body, "motor link", String(S.links.motors));
  }

  // -- the mission and its editor --------------------------------------------------------------
  function onMap(m) {
    const changed = m.revision !== S.map.revision;
    // not this page's own Send (one in flight is taken as the cause) nor the first map: said,
    // so neither page's "mission.load: ok" stands over a mission that is no longer theirs
    const foreign = changed && S.map.revision !== -1 && !S.sending && !S.ownRevisions.has(m.revision);
    S.map = m;
    if (foreign) {
      const n = m.waypoints.length, what = n ? n + " waypoints" : "no mission";
      if (S.dirty) {
        S.draftStale = true;
        S.replaceAsked = false;
        say("the robot's mission was replaced, not from this page: it has " + what + " now; your edits (not sent) were made on the one before", true);
      } else say("the robot's mission was replaced, not from this page: it has " + what + " now");
    }
    if (m.geofence && m.geofence.center && !S.originFromFence) {
      S.origin = m.geofence.center; // the frame stays put from here on
      S.originFromFence = true;
      S.track = [];
    }
    if (!changed) return missionShown(); // the launch point, the fence: the list stays
    if (!S.dirty) S.draft = m.waypoints.map((p) => p.slice());
    renderMission();
  }
  // the track the daemon kept before this page opened (after the map: the frame is set)
  function onTrack(points) {
    if (!S.origin && points.length) S.origin = points[0];
    // sent on every (re)connection: the daemon's track replaces the page's, which it
    // includes (prepending it doubled the track at each reconnection); an empty one too
    // (a restarted daemon without a fix yet: the old run's track is not this one's)
    S.track = S.origin ? points.map((p) => toLocal(p[0], p[1])) : [];
    redraw();
  }
  function setDraft(points) {
    S.draft = points;
    S.dirty = true;
    renderMission();
  }
  // the mission or the draft changed: its list, its state line and the map's mission layer
  function renderMission() {
    renderList();
    missionShown();
  }
  function missionShown() {
    S.missionVersion++;
    $("mission-state").textContent = S.dirty
      ? S.draft.length + " waypoints, edited: not sent"
      : S.map.waypoints.length ? S.map.waypoints.length + " waypoints on the robot" : "none loaded";
    redraw();
  }
  // The list holds rows for the part of it in view only (and a few beyond), drawn again when
  // it scrolls or the draft changes: 3000 rows built at once held the page (and its STOP).
  const ROW_PX = 18; // console.css: .wp-row's height
  const rowText = (p) => fmt(p[0], 7) + ", " + fmt(p[1], 7);
  function renderList() {
    const box = $("wp-list"), rows = $("wp-rows"), pts = S.draft;
    rows.style.height = pts.length * ROW_PX + "px";
    const first = Math.max(0, Math.floor(box.scrollTop / ROW_PX) - 4);
    const last = Math.min(pts.length, Math.ceil((box.scrollTop + (box.clientHeight || 150)) / ROW_PX) + 4);
    const deletable = S.info && !S.info.watch_only;
    const shown = document.createDocumentFragment();
    for (let i = first; i < last; i++) {
      const row = document.createElement("div");
      row.className = "wp-row";
      row.setAttribute("role", "listitem");
      row.style.top = i * ROW_PX + "px";
      const n = document.createElement("span");
      n.className = "n";
      n.textContent = i + 1 + ".";
      row.append(n, rowText(pts[i]));
      if (deletable) {
        const del = document.createElement("button");
        del.textContent = "×";
        del.title = "delete waypoint " + (i + 1);
        del.dataset.i = i; // one listener on the list (below), not one per row
        row.append(del);
      }
      shown.append(row);
    }
    rows.replaceChildren(shown);
  }
  $("wp-list").addEventListener("scroll", renderList, { passive: true });
  $("wp-list").addEventListener("click", (ev) => {
    const del = ev.target.closest("button[data-i]");
    if (!del) return;
    const i = Number(del.dataset.i);
    setDraft(S.draft.filter((_, j) => j !== i));
  });
  // Its reply may come seconds after the click (a Send held until a reconnected page's auth
  // succeeds, under the auth's back-off): the draft edited meanwhile is not what the robot
  // got. Only a draft still as sent is taken as on the robot; a later edit stays, not sent,
  // and the page says so (before, it was dropped and the page showed the old mission as sent).
  // By content, not by an edit counter: a drag edits in place, the browser's console assigns.
  async function sendMission() {
    if (!S.draft.length) return say("the mission has no waypoints", true);
    if (S.dirty && S.draftStale && !S.replaceAsked) {
      S.replaceAsked = true;
      const n = S.map.waypoints.length;
      return say("the robot's mission changed since your edits began (another page or client loaded " + n + " waypoints): Send again to replace it with your " + S.draft.length, true);
    }
    const sent = JSON.stringify(S.draft), n = S.draft.length, at = clock();
    S.sending++;
    let r;
    try {
      r = await command("mission.load", { waypoints: S.draft });
    } finally {
      S.sending--;
    }
    if (!r.ok) return;
    if (Array.isArray(r.notes) && r.notes.length) say("mission.load: ok; note: " + r.notes.join("; "), true);
    if (Number.isInteger(r.revision)) S.ownRevisions.add(r.revision);
    S.draftStale = S.replaceAsked = false;
    if (S.draft.length === n && JSON.stringify(S.draft) === sent) { S.dirty = false; renderMission(); }
    else if (S.dirty) say("mission.load: ok, but the robot has the mission as sent at " + at + " (" + n + " waypoints): your edits since are not sent", true);
  }
  const clock = () => new Date().toTimeString().slice(0, 8); // local HH:MM:SS
  const FORMATS = { gpx: "gpx", csv: "csv", kml: "kml", waypoints: "waypoints", plan: "plan" };
  function loadFile(file) {
    const limit = S.info ? S.info.max_message_bytes : Infinity;
    if (file.size > limit) return say(file.name + ": " + file.size + " bytes, too large to send: the console takes at most " + limit + " bytes (console.max_message_bytes)", true);
    const reader = new FileReader();
    // the file replaces the draft when the daemon has read it (later, if held until the auth):
    // an edit made meanwhile is replaced too, and the page says so
    const before = JSON.stringify(S.draft), wasDirty = S.dirty;
    reader.onload = async () => {
      const ext = file.name.split(".").pop().toLowerCase();
      const r = await request("mission.parse", { content: reader.result, format: FORMATS[ext] || null, name: file.name });
      if (r.ok) {
        const lost = S.dirty && (!wasDirty || JSON.stringify(S.draft) !== before) ? "; it replaced the edits made while it was read" : "";
        setDraft(r.waypoints);
        S.draftStale = S.replaceAsked = false;
        const notes = Array.isArray(r.notes) && r.notes.length ? "; note: " + r.notes.join("; ") : "";
        say(file.name + ": " + r.waypoints.length + " waypoints (not sent yet)" + lost + notes, Boolean(lost));
        fit();
      } else say(file.name + ": " + r.error.message, true);
    };
    reader.readAsText(file);
  }

  // -- recordings on the robot, through the log viewer (x6wd plot's page) ------------------------
  async function listRecordings() {
    const r = await request("recording.list");
    if (!r.ok) return say("recordings: " + r.error.message, true);
    const ul = $("recordings");
    ul.textContent = "";
    if (!r.recordings.length) ul.textContent = "none yet";
    for (const rec of r.recordings) {
      const li = document.createElement("li");
      const open = document.createElement("button");
      open.textContent = "Open";
      open.onclick = () => viewRecording(rec.name);
      // the run being written now: the viewer shows what is on disk so far
      const live = rec.in_progress ? ", still being recorded (this run)" : "";
      li.append(open, rec.name + " (" + (rec.bytes / 1e6).toFixed(1) + " MB" + live + ")");
      ul.append(li);
    }
  }
  async function viewRecording(name) {
    say("reading " + name + " ...");
    const r = await request("recording.view", { name: name });
    if (!r.ok) return say(name + ": " + r.error.message, true);
    $("rec-name").textContent = name;
    $("rec-frame").srcdoc = r.html; // sandboxed: its scripts run, it cannot reach this page
    $("rec-view").hidden = false;
    say(name + ": shown");
  }
  $("rec-list").onclick = listRecordings;
  $("rec-close").onclick = () => { $("rec-view").hidden = true; $("rec-frame").srcdoc = ""; };
  // The viewer's frame is sandboxed (another origin): a key pressed while it has the focus
  // never reaches this page, nor does the space bar's stop. So the focus is taken back from
  // it as soon as it gets it (a click in the frame still acts there; the wheel scrolls it).
  window.addEventListener("blur", () => setTimeout(() => {
    if (document.activeElement === $("rec-frame")) $("rec-view").focus();
  }, 0));

  // -- manual drive and its dead-man ------------------------------------------------------------
  const DIRECTIONS = { fwd: [1, 1], back: [-1, -1], left: [-0.7, 0.7], right: [0.7, -0.7] };
  // A press: from the button or key going down to its release. Every drive of it carries
  // press_ms, when it began (this page's clock, as sent_ms): the daemon refuses the drives of
  // a press that began before another client's stop, so a stop ends a held drive (the robot
  // stays stopped until the operator lets go and presses again).
  function startDrive(dir) {
    if (!S.info || S.info.watch_only) return;
    if (S.drive === dir) return;
    endDrive(false);
    S.drive = dir;
    const press = Math.round(performance.now());
    S.press = press;
    const state = { ok: false, inflight: 0, stopOnOk: false, busy: false };
    S.pressState = state;
    $("drive-stopped").hidden = true;
    $("drive-" + dir).classList.add("active");
    // A drive sent after a stall of the page (its main thread busy, timers and events held
    // back) longer than deadman_s: the daemon's dead-man has stopped the robot meanwhile, and
    // the finger may have been lifted during the stall (its release is queued behind this
    // tick). Such a tick ends the press instead of driving; the operator presses again.
    // Before (an outside audit): the overdue tick ran first and the robot got 40 % again for
    // 2-25 ms after the stall, until the queued release's stop. A stall is a gap longer than
    // deadman_s, at least 0.5 s, plus one tick: with a short deadman_s (0.1 s: ticks every
    // 50 ms) one tick a little late on a slow phone is no stall (a review: every press ended).
    const tickMs = Math.max(50, S.info.deadman_s * 1000 / 3);
    const stallMs = Math.max(S.info.deadman_s * 1000, 500) + tickMs;
    let lastSendAt = null;
    const send = () => {
      if (S.press !== press) return;
      const now = performance.now();
      if (lastSendAt !== null && now - lastSendAt > stallMs) {
        const text = "The page stalled " + ((now - lastSendAt) / 1000).toFixed(1) + " s: the dead-man stopped the robot and the drive ended. Release and press again to drive.";
        endDrive(false);
        say(text, true);
        $("drive-stopped").textContent = text;
        $("drive-stopped").hidden = false;
        return;
      }
      lastSendAt = now;
      const speed = Number($("speed").value);
      const [l, r] = DIRECTIONS[dir];
      state.inflight++;
      request("drive", { left: l * speed, right: r * speed, duration_s: S.info.deadman_s, press_ms: press }).then((r) => {
        state.inflight--;
        if (r.ok) {
          state.ok = true;
          // released before this answer: the drive runs now, so the release's stop goes now
          // (unless a new press of this page began: its drives replace this one)
          // so does one of a press refused "busy" before it (two drives in flight): the page
          // shows it ended, so the robot must not run this one
          if ((state.stopOnOk || state.busy) && S.press === null) {
            state.stopOnOk = state.busy = false;
            request("stop");
          }
          if (S.press === press) showDriver(null); // this page drives
          return;
        }
        // another client drives: said also for a press already let go (a tap)
        if (r.error.reason === "busy" && (S.press === press || S.press === null)) busyElsewhere(r.error.driver);
        if (S.press !== press) return; // a refusal of an ended press ends nothing
        if (r.error.reason === "busy") state.busy = true;
        if (r.error.reason === "stopped") stoppedElsewhere();
        else if (r.error.reason !== "busy") say("drive: " + r.error.message, true);
        endDrive(false);
      });
    };
    S.driveSend = send;
    send();
    // three sends per dead-man period: one lost or late message does not stop the robot
    S.driveTimer = setInterval(send, tickMs);
  }
  // this page's stops end its press before they are sent: a drive of the press held now
  // refused as "stopped" means a stop it did not send (another client's, or a page's)
  function stoppedElsewhere() {
    const text = "The robot was stopped by another client: the drive ended. Release and press again to drive.";
    say(text, true);
    $("drive-stopped").textContent = text;
    $("drive-stopped").hidden = false;
  }
  // another client's drive holds: the daemon refused this page's ("busy"); its press ends
  // and nothing is sent on its release (a stop then ended the other client's drive)
  function busyElsewhere(driver) {
    showDriver(driver || "unknown");
    say("drive refused: another client is driving (" + (driver || "unknown") + ") — Stop still works", true);
  }
  // who drives when it is not this page, under the drive buttons (null: nobody else)
  function showDriver(driver) {
    S.driver = driver;
    const el = $("drive-busy");
    el.hidden = !driver;
    if (driver) el.textContent = "Another client is driving (" + driver + ") — Stop still works.";
  }
  // The release of a press: its stop is sent only if this page's drive runs, i.e. a drive of
  // this press was obeyed ("ok"); one still unanswered sends the stop when it is obeyed. A
  // press refused ("busy": another client drives) sends nothing: a tap on a second page
  // stopped the other client's drive.
  function endDrive(sendStop) {
    if (S.driveTimer !== null) clearInterval(S.driveTimer);
    S.driveTimer = null;
    S.driveKey = null;
    S.press = null;
    S.driveSend = null;
    const state = S.pressState;
    S.pressState = null;
    if (S.drive === null) return;
    $("drive-" + S.drive).classList.remove("active");
    S.drive = null;
    if (!sendStop || !state) return;
    if (state.ok) request("stop");
    else if (state.inflight > 0) state.stopOnOk = true;
  }
  for (const dir of Object.keys(DIRECTIONS)) {
    const b = $("drive-" + dir);
    b.addEventListener("pointerdown", (ev) => { b.setPointerCapture(ev.pointerId); startDrive(dir); });
    for (const end of ["pointerup", "pointercancel", "lostpointercapture"]) b.addEventListener(end, () => endDrive(true));
  }
  // by the physical key (ev.code): ev.key of the same key changes with Shift and Caps Lock
  // ("w" down, "W" up), and a release that matched no drive never stopped it
  const KEYS = { ArrowUp: "fwd", KeyW: "fwd", ArrowDown: "back", KeyS: "back", ArrowLeft: "left", KeyA: "left", ArrowRight: "right", KeyD: "right" };
  const TEXT_INPUTS = new Set(["text", "password", "search", "email", "url", "tel", "number"]);
  const typing = (el) => el.isContentEditable || el.tagName === "TEXTAREA" ||
    (el.tagName === "INPUT" && TEXT_INPUTS.has(el.type));
  document.addEventListener("keydown", (ev) => {
    // the space bar stops whatever has focus (the speed slider, a button), but a space typed
    // into a text field (the token) is text
    if ((ev.code === "Space" || ev.key === " ") && !typing(ev.target)) {
      if (ev.repeat) endDrive(false); else stopNow(); // the stop first (it ends the drive too)
      ev.preventDefault();
      return;
    }
    // macOS sends no keyup for a key released while Cmd is down: the held key is lost
    if (ev.key === "Meta" && S.driveKey) { endDrive(true); return; }
    if (ev.target.tagName === "INPUT" || ev.repeat) return; // arrows move the slider
    const dir = KEYS[ev.code];
    if (dir) { ev.preventDefault(); startDrive(dir); if (S.drive === dir) S.driveKey = ev.code; }
  });
  document.addEventListener("keyup", (ev) => { if (S.driveKey && ev.code === S.driveKey) endDrive(true); });
  // the page going away, hidden or out of focus ends the drive at once
  document.addEventListener("visibilitychange", () => { if (document.hidden) endDrive(true); });
  // leaving the page (or its being kept in the back/forward cache) closes its link too
  window.addEventListener("pagehide", () => { endDrive(true); if (S.ws) S.ws.close(1001); });
  window.addEventListener("blur", () => endDrive(true));
  // a context menu takes the keyboard: the held key's release may never come here
  document.addEventListener("contextmenu", () => { if (S.driveKey) endDrive(true); });

  // -- the map --------------------------------------------------------------------------------------
  function niceStep(m) {
    const p = Math.pow(10, Math.floor(Math.log10(m)));
    for (const k of [1, 2, 5, 10]) if (k * p >= m) return k * p;
    return 10 * p;
  }
  function drawTiles(w, h) {
    const url = S.info && S.info.tile_url;
    if (!url || !S.origin) return;
    const lat0 = S.origin[0];
    const mpp = 1 / S.view.pxPerM;
    const z = Math.max(0, Math.min(19, Math.round(Math.log2(156543.03 * Math.cos(lat0 * Math.PI / 180) / mpp))));
    const n = Math.pow(2, z);
    const tileOf = (lat, lon) => {
      const r = lat * Math.PI / 180;
      return [(lon + 180) / 360 * n, (1 - Math.log(Math.tan(r) + 1 / Math.cos(r)) / Math.PI) / 2 * n];
    };
    const latOf = (y) => Math.atan(Math.sinh(Math.PI * (1 - 2 * y / n))) * 180 / Math.PI;
    const [e0, n0] = fromScreen(0, h);
    const [e1, n1] = fromScreen(w, 0);
    const [la0, lo0] = toLatLon(e0, n0);
    const [la1, lo1w] = toLatLon(e1, n1);
    // a view across the 180th meridian: its east edge comes back wrapped (-179.99...);
    // unwrapped, the tile columns run on past n and the modulo below wraps them
    const lo1 = lo1w < lo0 ? lo1w + 360 : lo1w;
    const [x0, y1] = tileOf(la0, lo0);
    const [x1, y0] = tileOf(la1, lo1);
    for (let x = Math.floor(x0); x <= Math.floor(x1); x++) {
      for (let y = Math.floor(y0); y <= Math.floor(y1); y++) {
        if (y < 0 || y >= n) continue;
        const src = url.replace("{z}", z).replace("{x}", ((x % n) + n) % n).replace("{y}", y);
        let img = S.tiles.get(src);
        if (!img) {
          img = new Image();
          img.onload = redraw;
          img.src = src;
          S.tiles.set(src, img);
          if (S.tiles.size > 400) S.tiles.delete(S.tiles.keys().next().value);
        }
        if (!img.complete || !img.naturalWidth) continue;
        const [ax, ay] = toScreen(...toLocal(latOf(y), x / n * 360 - 180));
        const [bx, by] = toScreen(...toLocal(latOf(y + 1), (x + 1) / n * 360 - 180));
        ctx.drawImage(img, ax, ay, bx - ax, by - ay);
      }
    }
  }
  // The map is drawn when something on it changed (telemetry, the mission or the draft, the
  // view, the window's size, a tile that arrived), at most once every MIN_DRAW_MS. Before, it
  // was drawn at every animation frame: with a 3000-waypoint mission in the editor the page
  // spent ~10 s of every 11 s drawing, and STOP took 5-11 s to reach the robot (outside audit).
  const MIN_DRAW_MS = 80;
  S.redraw = () => redraw(); // for a change made from the browser's console
  let drawQueued = false, lastDrawAt = -Infinity;
  function redraw() {
    if (drawQueued) return;
    drawQueued = true;
    setTimeout(() => requestAnimationFrame(() => {
      drawQueued = false;
      lastDrawAt = performance.now();
      draw();
      S.drawMs += performance.now() - lastDrawAt;
    }), Math.max(0, lastDrawAt + MIN_DRAW_MS - performance.now()));
  }
  // The track and the mission are drawn on canvases of their own, kept while they and the
  // view's scale stay as they are: each frame only copies them. A layer covers the view and
  // MARGIN pixels beyond each side, so panning (and "follow robot") moves it; it is drawn
  // again once the view has moved more than that. The track layer takes the new points only.
  const MARGIN = 160; // CSS px
  const LABELS_MAX = 400; // more waypoints than this on the layer: circles without numbers
  const LABEL_PX = 16; // a number closer than this to one already written is left out
  const layer = () => { const c = document.createElement("canvas"); return { c: c, g: c.getContext("2d") }; };
  const L = { geo: null, track: layer(), mission: layer() };
  function layerGeometry(w, h, dpr) {
    const v = S.view, g = L.geo;
    if (g && g.k === v.pxPerM && g.w === w && g.h === h && g.dpr === dpr &&
        g.lat0 === S.origin[0] && g.lon0 === S.origin[1] &&
        Math.abs(g.e - v.e) * g.k <= MARGIN && Math.abs(g.n - v.n) * g.k <= MARGIN) return g;
    L.geo = { id: g ? g.id + 1 : 1, e: v.e, n: v.n, k: v.pxPerM, w: w, h: h, dpr: dpr, lat0: S.origin[0], lon0: S.origin[1] };
    return L.geo;
  }
  // layer pixels of local metres
  const onLayer = (g, e, n) => [MARGIN + g.w / 2 + (e - g.e) * g.k, MARGIN + g.h / 2 - (n - g.n) * g.k];
  function clearLayer(l, g) {
    const W = Math.round((g.w + 2 * MARGIN) * g.dpr), H = Math.round((g.h + 2 * MARGIN) * g.dpr);
    if (l.c.width !== W || l.c.height !== H) { l.c.width = W; l.c.height = H; }
    l.g.setTransform(g.dpr, 0, 0, g.dpr, 0, 0);
    l.g.clearRect(0, 0, g.w + 2 * MARGIN, g.h + 2 * MARGIN);
    l.geo = g.id;
    S.layerDraws++;
  }
  function drawTrackLayer(g) {
    const l = L.track, pts = S.track;
    let from = 0;
    if (l.geo !== g.id || l.pts !== pts || l.epoch !== S.trackEpoch || l.n > pts.length) {
      clearLayer(l, g);
      l.pts = pts;
      l.epoch = S.trackEpoch;
    } else if (l.n === pts.length) return;
    else from = Math.max(0, l.n - 1); // the points added since: from the last one drawn
    const c = l.g;
    c.strokeStyle = "#2e7d32";
    c.lineWidth = 2;
    c.beginPath();
    for (let i = from; i < pts.length; i++) {
      const [x, y] = onLayer(g, pts[i][0], pts[i][1]);
      if (i > from) c.lineTo(x, y); else c.moveTo(x, y);
    }
    c.stroke();
    l.n = pts.length;
  }
  function drawMissionLayer(g) {
    const l = L.mission;
    if (l.geo === g.id && l.version === S.missionVersion) return;
    clearLayer(l, g);
    l.version = S.missionVersion;
    const c = l.g;
    // the robot's mission (orange) and, when edited, the draft (blue)
    polyline(c, g, S.map.waypoints, S.dirty ? "rgba(230,81,0,0.35)" : "#e65100", 2);
    if (S.dirty) polyline(c, g, S.draft, "#1565c0", 2, [6, 4]);
    // the markers on the layer (those beyond it are not drawn), in one path
    const pts = S.dirty ? S.draft : S.map.waypoints;
    const W = g.w + 2 * MARGIN, H = g.h + 2 * MARGIN;
    const shown = [];
    c.fillStyle = S.dirty ? "#1565c0" : "#e65100";
    c.beginPath();
    for (let i = 0; i < pts.length; i++) {
      const [x, y] = onLayer(g, ...toLocal(pts[i][0], pts[i][1]));
      if (x < -10 || y < -10 || x > W + 10 || y > H + 10) continue;
      c.moveTo(x + 8, y);
      c.arc(x, y, 8, 0, 2 * Math.PI);
      shown.push([i, x, y]);
    }
    c.fill();
    // their numbers: none when there are too many to read, none over another's
    if (shown.length > LABELS_MAX) return;
    c.fillStyle = "#fff";
    c.font = "bold 10px sans-serif";
    c.textAlign = "center";
    c.textBaseline = "middle";
    const taken = new Map();
    for (const [i, x, y] of shown) {
      const cx = Math.floor(x / LABEL_PX), cy = Math.floor(y / LABEL_PX);
      let free = true;
      for (let a = cx - 1; a <= cx + 1 && free; a++) {
        for (let b = cy - 1; b <= cy + 1 && free; b++) {
          const q = taken.get(a + "," + b);
          if (q && Math.abs(q[0] - x) < LABEL_PX && Math.abs(q[1] - y) < LABEL_PX) free = false;
        }
      }
      if (!free) continue;
      taken.set(cx + "," + cy, [x, y]);
      c.fillText(String(i + 1), x, y);
    }
  }
  // a line through the points, its legs cut to the layer (a dashed leg far beyond it, zoomed
  // in, was dashed along its whole length)
  function polyline(c, g, points, color, width, dash) {
    if (points.length < 1) return;
    c.strokeStyle = color;
    c.lineWidth = width;
    c.setLineDash(dash || []);
    c.beginPath();
    const W = g.w + 2 * MARGIN, H = g.h + 2 * MARGIN;
    let a = onLayer(g, ...toLocal(points[0][0], points[0][1]));
    let at = null; // where the path is now (null: nowhere)
    if (points.length === 1) c.moveTo(a[0], a[1]);
    for (let i = 1; i < points.length; i++) {
      const b = onLayer(g, ...toLocal(points[i][0], points[i][1]));
      const cut = clip(a[0], a[1], b[0], b[1], -10, -10, W + 10, H + 10);
      if (cut) {
        if (!at || at[0] !== cut[0] || at[1] !== cut[1]) c.moveTo(cut[0], cut[1]);
        c.lineTo(cut[2], cut[3]);
        at = [cut[2], cut[3]];
      } else at = null;
      a = b;
    }
    c.stroke();
    c.setLineDash([]);
  }
  // the part of the segment (x0, y0)-(x1, y1) in the box, or null (Liang-Barsky)
  function clip(x0, y0, x1, y1, xmin, ymin, xmax, ymax) {
    const dx = x1 - x0, dy = y1 - y0;
    let t0 = 0, t1 = 1;
    for (const [p, q] of [[-dx, x0 - xmin], [dx, xmax - x0], [-dy, y0 - ymin], [dy, ymax - y0]]) {
      if (p === 0) { if (q < 0) return null; continue; }
      const r = q / p;
      if (p < 0) { if (r > t1) return null; if (r > t0) t0 = r; } else { if (r < t0) return null; if (r < t1) t1 = r; }
    }
    return [x0 + t0 * dx, y0 + t0 * dy, x0 + t1 * dx, y0 + t1 * dy];
  }
  function marker(x, y, label, fill, ink) {
    ctx.fillStyle = fill;
    ctx.beginPath();
    ctx.arc(x, y, 8, 0, 2 * Math.PI);
    ctx.fill();
    ctx.fillStyle = ink;
    ctx.font = "bold 10px sans-serif";
    ctx.textAlign = "center";
    ctx.textBaseline = "middle";
    ctx.fillText(label, x, y);
  }
  function draw() {
    S.draws++;
    const w = canvas.clientWidth, h = canvas.clientHeight;
    const dpr = window.devicePixelRatio || 1;
    if (canvas.width !== Math.round(w * dpr) || canvas.height !== Math.round(h * dpr)) {
      canvas.width = Math.round(w * dpr);
      canvas.height = Math.round(h * dpr);
    }
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.clearRect(0, 0, w, h);
    if (!S.origin) {
      ctx.fillStyle = "#777";
      ctx.fillText("waiting for the first fix…", 20, 60);
      return;
    }
    if (!w || !h) return; // not laid out (yet)
    drawTiles(w, h);
    // grid, every "nice" number of metres ~80 px apart, and the scale
    const step = niceStep(80 / S.view.pxPerM);
    const [ea, na] = fromScreen(0, h);
    const [eb, nb] = fromScreen(w, 0);
    ctx.strokeStyle = "rgba(0,0,0,0.08)";
    ctx.lineWidth = 1;
    ctx.beginPath();
    for (let e = Math.ceil(ea / step) * step; e <= eb; e += step) { const x = toScreen(e, 0)[0]; ctx.moveTo(x, 0); ctx.lineTo(x, h); }
    for (let n = Math.ceil(na / step) * step; n <= nb; n += step) { const y = toScreen(0, n)[1]; ctx.moveTo(0, y); ctx.lineTo(w, y); }
    ctx.stroke();
    const scale = "grid " + step + " m · N up";
    if ($("map-scale").textContent !== scale) $("map-scale").textContent = scale;
    const fence = S.map.geofence;
    if (fence && fence.center) {
      const [cx, cy] = toScreen(...toLocal(fence.center[0], fence.center[1]));
      ctx.strokeStyle = "#c62828";
      ctx.setLineDash([8, 6]);
      ctx.lineWidth = 2;
      ctx.beginPath();
      ctx.arc(cx, cy, fence.radius_m * S.view.pxPerM, 0, 2 * Math.PI);
      ctx.stroke();
      ctx.setLineDash([]);
    }
    // the track under the mission, both from their layers (at whole device pixels)
    const g = layerGeometry(w, h, dpr);
    drawTrackLayer(g);
    drawMissionLayer(g);
    const x0 = Math.round((-MARGIN + (g.e - S.view.e) * g.k) * dpr) / dpr;
    const y0 = Math.round((-MARGIN + (S.view.n - g.n) * g.k) * dpr) / dpr;
    if (S.track.length) ctx.drawImage(L.track.c, x0, y0, w + 2 * MARGIN, h + 2 * MARGIN);
    if (S.map.waypoints.length || (S.dirty && S.draft.length)) ctx.drawImage(L.mission.c, x0, y0, w + 2 * MARGIN, h + 2 * MARGIN);
    // the current target (yellow) over the mission
    const pts = S.dirty ? S.draft : S.map.waypoints;
    const target = S.tel && !S.dirty ? S.tel.waypoint_index : null;
    if (target !== null && target >= 0 && target < pts.length) {
      const [x, y] = toScreen(...toLocal(pts[target][0], pts[target][1]));
      marker(x, y, String(target + 1), "#ffd600", "#000");
    }
    if (S.map.launch) {
      const [x, y] = toScreen(...toLocal(S.map.launch[0], S.map.launch[1]));
      ctx.fillStyle = "#6a1b9a";
      ctx.fillRect(x - 8, y - 8, 16, 16);
      ctx.fillStyle = "#fff";
      ctx.font = "bold 11px sans-serif";
      ctx.textAlign = "center";
      ctx.textBaseline = "middle";
      ctx.fillText("H", x, y);
    }
    // the raw fix and the robot (heading true)
    const t = S.tel;
    if (t && t.lat_deg !== null) {
      const [x, y] = toScreen(...toLocal(t.lat_deg, t.lon_deg));
      ctx.fillStyle = "rgba(0,0,0,0.35)";
      ctx.beginPath();
      ctx.arc(x, y, 3, 0, 2 * Math.PI);
      ctx.fill();
    }
    if (S.track.length) {
      const p = S.track[S.track.length - 1];
      const [x, y] = toScreen(p[0], p[1]);
      ctx.save();
      ctx.translate(x, y);
      ctx.rotate(((t && t.heading_deg) || 0) * Math.PI / 180);
      ctx.fillStyle = S.stale ? "#9e9e9e" : "#1b5e20"; // grey: where it was, not where it is
      ctx.strokeStyle = "#fff";
      ctx.beginPath();
      ctx.moveTo(0, -14); ctx.lineTo(9, 10); ctx.lineTo(0, 5); ctx.lineTo(-9, 10); ctx.closePath();
      ctx.fill();
      ctx.stroke();
      ctx.restore();
    }
  }
  function fit() {
    const pts = (S.dirty ? S.draft : S.map.waypoints).map((p) => toLocal(p[0], p[1]));
    if (S.map.launch) pts.push(toLocal(S.map.launch[0], S.map.launch[1]));
    for (const p of S.track) pts.push(p);
    if (!S.origin || !pts.length) return;
    const es = pts.map((p) => p[0]), ns = pts.map((p) => p[1]);
    const [emin, emax, nmin, nmax] = [Math.min(...es), Math.max(...es), Math.min(...ns), Math.max(...ns)];
    S.view.e = (emin + emax) / 2;
    S.view.n = (nmin + nmax) / 2;
    const span = Math.max(emax - emin, nmax - nmin, 10) * 1.3;
    S.view.pxPerM = Math.min(canvas.clientWidth, canvas.clientHeight) / span;
    $("follow").checked = false;
    redraw();
  }
  // pointer: drag a draft waypoint, pan, click to add; right-click deletes; wheel zooms
  function hit(x, y) {
    const pts = S.dirty ? S.draft : S.map.waypoints;
    for (let i = pts.length - 1; i >= 0; i--) {
      const [px, py] = toScreen(...toLocal(pts[i][0], pts[i][1]));
      if (Math.hypot(px - x, py - y) <= 10) return i;
    }
    return -1;
  }
  // One pointer (a mouse, a finger): drag a waypoint, pan, or a click/tap that adds one. Two
  // fingers: pinch to zoom about their middle, which also pans with them. The map takes its
  // touches itself (touch-action: none): before (an outside audit), the browser took a
  // one-finger drag (pointercancel after its first move, "follow robot" already switched off)
  // and a pinch zoomed the whole page 4.2x, STOP out of view.
  let drag = null, pinch = null;
  const fingers = new Map(); // pointerId -> [x, y] on the canvas
  const editable = () => S.origin && S.info && !S.info.watch_only;
  const at = (ev) => { const r = canvas.getBoundingClientRect(); return [ev.clientX - r.left, ev.clientY - r.top]; };
  function startPinch() {
    const [a, b] = [...fingers.values()];
    const mid = [(a[0] + b[0]) / 2, (a[1] + b[1]) / 2];
    pinch = { d: Math.max(1, Math.hypot(a[0] - b[0], a[1] - b[1])), k: S.view.pxPerM, at: fromScreen(...mid) };
  }
  canvas.addEventListener("pointerdown", (ev) => {
    if (ev.button !== 0) return;
    canvas.setPointerCapture(ev.pointerId);
    const [x, y] = at(ev);
    fingers.set(ev.pointerId, [x, y]);
    if (fingers.size === 2) { drag = null; startPinch(); return; } // a waypoint dragged stays where it is
    if (fingers.size > 2) return;
    const i = editable() ? hit(x, y) : -1;
    drag = { id: ev.pointerId, i: i, x: x, y: y, moved: false, e: S.view.e, n: S.view.n };
  });
  canvas.addEventListener("pointermove", (ev) => {
    if (!fingers.has(ev.pointerId)) return;
    const [x, y] = at(ev);
    fingers.set(ev.pointerId, [x, y]);
    if (pinch) {
      if (fingers.size !== 2) return;
      const [a, b] = [...fingers.values()];
      const d = Math.max(1, Math.hypot(a[0] - b[0], a[1] - b[1]));
      S.view.pxPerM = Math.max(0.01, Math.min(200, pinch.k * d / pinch.d));
      // the place first under the fingers' middle stays under it
      const now = fromScreen((a[0] + b[0]) / 2, (a[1] + b[1]) / 2);
      S.view.e += pinch.at[0] - now[0];
      S.view.n += pinch.at[1] - now[1];
      redraw();
      return;
    }
    if (!drag || drag.id !== ev.pointerId) return;
    if (Math.hypot(x - drag.x, y - drag.y) > 3) drag.moved = true;
    if (!drag.moved) return;
    if (drag.i >= 0) {
      if (!S.dirty) { S.draft = S.map.waypoints.map((p) => p.slice()); S.dirty = true; }
      S.draft[drag.i] = toLatLon(...fromScreen(x, y));
      renderMission();
    } else {
      $("follow").checked = false;
      S.view.e = drag.e - (x - drag.x) / S.view.pxPerM;
      S.view.n = drag.n + (y - drag.y) / S.view.pxPerM;
      redraw();
    }
  });
  // a pointer's end: lifted (pointerup: a tap may add a waypoint) or taken (pointercancel)
  function pointerEnd(ev, lifted) {
    if (!fingers.delete(ev.pointerId)) return;
    if (lifted && drag && drag.id === ev.pointerId && !drag.moved && drag.i < 0 && S.adding && editable()) {
      const base = S.dirty ? S.draft : S.map.waypoints.map((p) => p.slice());
      setDraft(base.concat([toLatLon(...fromScreen(...at(ev)))]));
    }
    if (drag && drag.id === ev.pointerId) drag = null;
    if (pinch && fingers.size < 2) {
      pinch = null;
      // the finger left on the map pans on from where it is (never a tap: it adds nothing)
      for (const [id, [x, y]] of fingers) drag = { id: id, i: -1, x: x, y: y, moved: true, e: S.view.e, n: S.view.n };
    } else if (fingers.size === 2) startPinch();
  }
  canvas.addEventListener("pointerup", (ev) => pointerEnd(ev, true));
  canvas.addEventListener("pointercancel", (ev) => pointerEnd(ev, false));
  canvas.addEventListener("lostpointercapture", (ev) => pointerEnd(ev, false));
  canvas.addEventListener("contextmenu", (ev) => {
    ev.preventDefault();
    const i = editable() ? hit(ev.offsetX, ev.offsetY) : -1;
    if (i >= 0) {
      const base = S.dirty ? S.draft : S.map.waypoints;
      setDraft(base.filter((_, j) => j !== i));
    }
  });
  canvas.addEventListener("wheel", (ev) => {
    ev.preventDefault();
    const before = fromScreen(ev.offsetX, ev.offsetY);
    S.view.pxPerM = Math.max(0.01, Math.min(200, S.view.pxPerM * Math.pow(1.0015, -ev.deltaY)));
    const after = fromScreen(ev.offsetX, ev.offsetY);
    S.view.e += before[0] - after[0];
    S.view.n += before[1] - after[1];
    redraw();
  }, { passive: false });

  // -- buttons ------------------------------------------------------------------------------------------
  for (const cmd of ["start", "pause", "resume", "return"]) {
    $("btn-" + cmd).addEventListener("click", () => command(cmd));
  }
  // STOP acts when it is pressed (pointerdown), not when it is let go, and its message is sent
  // before anything else is done. The click that follows the same press sends nothing more;
  // a click without a press (Enter on the focused button, assistive tools) stops.
  let stopPressedAt = -Infinity;
  $("btn-stop").addEventListener("pointerdown", (ev) => {
    if (ev.button !== 0) return;
    stopNow();
    stopPressedAt = performance.now();
  });
  $("btn-stop").addEventListener("click", (ev) => {
    if (ev.detail > 0 && performance.now() - stopPressedAt < 2000) return;
    stopNow();
  });
  $("btn-add").addEventListener("click", () => {
    S.adding = !S.adding;
    $("btn-add").setAttribute("aria-pressed", String(S.adding));
  });
  $("btn-fit").addEventListener("click", fit);
  $("btn-send").addEventListener("click", sendMission);
  $("btn-revert").addEventListener("click", () => { S.dirty = S.draftStale = S.replaceAsked = false; S.draft = S.map.waypoints.map((p) => p.slice()); renderMission(); });
  $("btn-clear").addEventListener("click", () => setDraft([]));
  $("mission-file").addEventListener("change", (ev) => { if (ev.target.files[0]) loadFile(ev.target.files[0]); ev.target.value = ""; });
  $("speed").addEventListener("input", () => { $("speed-out").textContent = $("speed").value; });
  $("token-form").addEventListener("submit", (ev) => { ev.preventDefault(); auth($("token-input").value); });

  // a token in the address (#token=...) is taken and removed from it: never sent to the server
  // in a URL, nor left in the history; also when it is typed into an open page's address
  function takeToken() {
    const m = /[#&]token=([^&]*)/.exec(location.hash);
    if (!m) return null;
    history.replaceState(null, "", location.pathname + location.search); // first: whatever follows
    let token = m[1];
    try { token = decodeURIComponent(token); } catch (e) { /* a malformed escape (%zz): as written */ }
    if (token) sessionStorage.setItem("x6wd-token", token);
    return token;
  }
  takeToken();
  window.addEventListener("hashchange", () => {
    const token = takeToken();
    if (token && S.info && S.info.auth_required && !S.authed) auth(token); // the token box is up
  });
  // the top bar's height (it grows as the pills wrap): the overlays on a narrow screen start below it
  const bar = document.querySelector("header");
  const barHeight = () => document.documentElement.style.setProperty("--header-h", bar.offsetHeight + "px");
  if (window.ResizeObserver) new ResizeObserver(barHeight).observe(bar);
  barHeight();
  $("follow").addEventListener("change", redraw);
  window.addEventListener("resize", redraw);
  if (window.ResizeObserver) new ResizeObserver(redraw).observe(canvas);
  // and once a second whatever happened (a change made from the browser's console)
  setInterval(redraw, 1000);
  connect();
  redraw();
})();
