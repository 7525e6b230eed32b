// gdwm dashboard: fragments rendered by the server replace parts of a page in place (no reload); the charts are
// Plotly figures built by the server and drawn with the plotly.min.js the Python package ships.
"use strict";
const gdwm = (() => {
  const banner = (text) => {
    const b = document.getElementById("banner");
    if (!b) return;
    b.hidden = !text;
    b.textContent = text || "";
  };

  async function getJson(url) {
    let r;
    try {
      r = await fetch(url, { headers: { Accept: "application/json" } });
    } catch (e) {
      banner("the dashboard does not answer (" + e + ")");
      return null;
    }
    if (r.status === 503) {
      const body = await r.json().catch(() => ({}));
      banner(body.error || "the store is not reachable");
      return null;
    }
    if (!r.ok) {
      banner(url + ": HTTP " + r.status);
      return null;
    }
    banner("");
    return r.json();
  }

  function replace(id, html) {
    const el = document.getElementById(id);
    if (el && html !== undefined && el.innerHTML !== html) el.innerHTML = html;
  }

  function draw(el, figure) {
    if (!el) return;
    if (!figure || !figure.data) {
      el.innerHTML = '<p class="muted">nothing to plot</p>';
      return;
    }
    if (!el.dataset.drawn) el.innerHTML = "";
    el.dataset.drawn = "1";
    Plotly.react(el, figure.data, figure.layout, { responsive: true, displaylogo: false });
  }

  function whenPlotly(fn) {
    if (window.Plotly) fn();
    else window.addEventListener("load", fn);
  }

  function pollHtml(url, id, seconds) {
    const tick = async () => {
      const d = await getJson(url);
      if (d) replace(id, d.html);
      setTimeout(tick, seconds * 1000);
    };
    setTimeout(tick, seconds * 1000);
  }

  function sweepPage() {
    const cfg = JSON.parse(document.getElementById("page-data").textContent);
    let version = cfg.table_version;
    let chartsVersion = -1;
    let effectsReady = false;

    let stagesShown = "";
    let picked = false; // the user chose a stage: keep it when the list grows
    function stages(list) {
      if (list.join("|") === stagesShown) return;
      stagesShown = list.join("|");
      const sel = document.getElementById("curve-stage");
      const had = sel.value;
      sel.innerHTML = list.map((s) => `<option>${s}</option>`).join("");
      if (picked && list.includes(had)) sel.value = had;
      if (list.length) curves();
    }

    async function charts() {
      const d = await getJson(cfg.charts);
      if (!d) return;
      stages(d.stages || []);
      if (!d.ready) return;
      if (d.version !== chartsVersion) {
        draw(document.getElementById("chart-values"), d.values);
        draw(document.getElementById("chart-parallel"), d.parallel);
        chartsVersion = d.version;
      }
      if (d.effects_ready) draw(document.getElementById("chart-effects"), d.effects);
      effectsReady = d.effects_ready;
    }

    async function curves() {
      const stage = document.getElementById("curve-stage").value;
      const d = await getJson(cfg.curves + "?stage=" + encodeURIComponent(stage));
      if (d) draw(document.getElementById("chart-curves"), d.figure);
    }
    document.getElementById("curve-stage").addEventListener("change", () => {
      picked = true;
      curves();
    });

    async function tick() {
      const d = await getJson(cfg.live);
      if (d) {
        replace("head", d.head);
        replace("grid", d.grid);
        replace("table", d.table);
        if (d.table_version !== version || chartsVersion < 0 || !effectsReady) {
          version = d.table_version;
          await charts();
        }
        if (d.settled && effectsReady) return; // the sweep is over and everything is computed
      }
      setTimeout(tick, cfg.poll_s * 1000);
    }
    whenPlotly(() => {
      charts();
      setTimeout(tick, cfg.settled ? 0 : cfg.poll_s * 1000);
    });
  }

  function whyFill(url) {
    const tick = async () => {
      const d = await getJson(url);
      if (!d) return setTimeout(tick, 3000);
      for (const td of document.querySelectorAll("td.why")) {
        const text = (d.why || {})[td.dataset.stage];
        if (text) td.textContent = text;
        else if (d.ready && td.textContent.trim() === "…") td.textContent = d.error ? "(" + d.error + ")" : "";
      }
      if (!d.ready) setTimeout(tick, 3000);
    };
    tick();
  }

  function drawStored(selector) {
    whenPlotly(() => {
      for (const el of document.querySelectorAll(selector)) draw(el, JSON.parse(el.dataset.figure));
    });
  }

  return { pollHtml, sweepPage, whyFill, drawStored };
})();
