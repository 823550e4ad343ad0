/* PackPilot report charts: unpack the inline series and draw them with the bundled uPlot.
 *
 * Everything is in the page: the data (the JSON block with id "pp-data"), uPlot and
 * this file. Zoom: drag across a chart, or turn the wheel over it; double-click or "reset zoom"
 * goes back to the whole run. Charts of one group share the cursor (hover shows every value at
 * that time in each chart's legend) and the zoom. For tests: window.ppCharts maps a chart id to
 * its uPlot, <body data-charts="drawn/total"> counts the drawn charts.
 */
(function () {
  "use strict";
  var DATA = JSON.parse(document.getElementById("pp-data").textContent);
  var charts = {};
  var groups = {};
  var zoomed = {};  // group -> [min, max] the user zoomed it to (null: the whole run)
  var cache = {};
  var drawn = 0;
  var total = 0;
  var syncing = false;
  var SPAN = DATA.span[1] - DATA.span[0];
  var TIME_INCRS = [0.1, 0.2, 0.5, 1, 2, 5, 10, 15, 30, 60, 120, 300, 600, 900, 1800, 3600, 7200,
    10800, 21600, 43200, 86400];
  window.ppCharts = charts;

  function b64bytes(text) {
    var bin = atob(text);
    var out = new Uint8Array(bin.length);
    for (var i = 0; i < bin.length; i++) { out[i] = bin.charCodeAt(i); }
    return out;
  }

  function decode(key) {
    if (cache[key]) { return cache[key]; }
    var rec = DATA.store[key];
    var stream = new Blob([b64bytes(rec.z)]).stream().pipeThrough(new DecompressionStream("deflate"));
    cache[key] = new Response(stream).arrayBuffer().then(function (buf) {
      var d = new Int32Array(buf);
      var out = new Array(rec.n);
      var acc = 0;
      for (var i = 0; i < rec.n; i++) { acc += d[i]; out[i] = acc * rec.q; }
      (rec.nan || []).forEach(function (r) {
        for (var k = r[0]; k < r[1]; k++) { out[k] = null; }
      });
      return out;
    });
    return cache[key];
  }

  function pad(n, w) { var s = String(n); while (s.length < w) { s = "0" + s; } return s; }

  function fmtT(t) {
    if (t == null || !isFinite(t)) { return "–"; }
    var neg = t < 0; t = Math.abs(t);
    var h = Math.floor(t / 3600), m = Math.floor((t % 3600) / 60), s = t % 60;
    var txt = h + ":" + pad(m, 2) + ":" + pad(s.toFixed(1), 4);
    return (neg ? "-" : "") + txt;
  }

  function fmtTick(t) {
    if (SPAN <= 600) { return fmtNum(t); }
    var h = Math.floor(t / 3600), m = Math.floor((t % 3600) / 60), s = Math.round(t % 60);
    return h + ":" + pad(m, 2) + (s ? ":" + pad(s, 2) : "");
  }

  function fmtNum(v) {
    if (v == null || !isFinite(v)) { return "–"; }
    var a = Math.abs(v);
    if (a === 0) { return "0"; }
    if (a >= 1e5 || a < 1e-3) { return v.toExponential(2); }
    return String(Number(v.toPrecision(4)));
  }

  function valueFmt(spec, s) {
    var cats = spec.categories;
    var off = s.offset || 0;
    var unit = spec.unit ? " " + spec.unit : "";
    var states = s.states;
    var sc = s.scale || 1;
    return function (u, v) {
      if (v == null) { return "–"; }
      if (states) { var j = Math.round((v - off) / sc); return j >= 0 && j < states.length ? states[j] : "–"; }
      if (cats) { var k = Math.round(v - off); return k >= 0 && k < cats.length ? cats[k] : "–"; }
      return fmtNum(v) + unit;
    };
  }

  function shade(spec) {
    return {
      hooks: {
        drawClear: [function (u) {
          if (!spec.bands) { return; }
          var ctx = u.ctx, top = u.bbox.top, h = u.bbox.height;
          ctx.save();
          ctx.globalAlpha = 0.22;
          spec.bands.forEach(function (b) {
            var x0 = u.valToPos(b[0], "x", true), x1 = u.valToPos(b[1], "x", true);
            ctx.fillStyle = b[2];
            ctx.fillRect(x0, top, Math.max(x1 - x0, 1), h);
          });
          ctx.restore();
        }],
        draw: [function (u) {
          if (!spec.marks) { return; }
          var ctx = u.ctx, top = u.bbox.top, h = u.bbox.height;
          ctx.save();
          ctx.setLineDash([4, 3]);
          ctx.lineWidth = 1.5;
          spec.marks.forEach(function (m) {
            var x = Math.round(u.valToPos(m[0], "x", true)) + 0.5;
            if (x < u.bbox.left || x > u.bbox.left + u.bbox.width) { return; }
            ctx.strokeStyle = m[1];
            ctx.beginPath(); ctx.moveTo(x, top); ctx.lineTo(x, top + h); ctx.stroke();
          });
          ctx.restore();
        }]
      }
    };
  }

  function wheelZoom(x0, x1) {
    return {
      hooks: {
        ready: [function (u) {
          u.over.addEventListener("wheel", function (e) {
            e.preventDefault();
            var rect = u.over.getBoundingClientRect();
            var at = u.posToVal(e.clientX - rect.left, "x");
            var min = u.scales.x.min, max = u.scales.x.max;
            var f = e.deltaY < 0 ? 0.75 : 1 / 0.75;
            var lo = at - (at - min) * f, hi = at + (max - at) * f;
            if (hi - lo >= x1 - x0) { lo = x0; hi = x1; }
            if (lo < x0) { hi += x0 - lo; lo = x0; }
            if (hi > x1) { lo -= hi - x1; hi = x1; }
            u.setScale("x", { min: Math.max(lo, x0), max: Math.min(hi, x1) });
          }, { passive: false });
        }]
      }
    };
  }

  function onScale(u, key) {
    // uPlot sets each chart's scale while building it: only a scale change after that (a
    // zoom) moves the group, else a chart on its own time axis (the CAN rates, which start
    // at the first frame) would narrow every other chart as the page loads
    if (key !== "x" || syncing || !u.ppReady) { return; }
    var eps = (u.ppX[1] - u.ppX[0]) * 1e-6;
    var full = u.scales.x.min <= u.ppX[0] + eps && u.scales.x.max >= u.ppX[1] - eps;
    // a chart showing its whole range puts the others on theirs (a chart on its own time
    // axis, like the CAN rates from the first frame, must not narrow the rest); a zoom
    // puts every chart of the group on the same span
    syncing = true;
    var group = groups[u.ppGroup] || [];
    group.forEach(function (o) {
      if (o === u) { return; }
      var lo = full ? o.ppX[0] : u.scales.x.min, hi = full ? o.ppX[1] : u.scales.x.max;
      if (o.scales.x.min !== lo || o.scales.x.max !== hi) { o.setScale("x", { min: lo, max: hi }); }
    });
    syncing = false;
    zoomed[u.ppGroup] = full ? null : [u.scales.x.min, u.scales.x.max];
    var label = document.querySelector('[data-range="' + u.ppGroup + '"]');
    if (label) {
      label.textContent = full ? "whole run" : fmtT(u.scales.x.min) + " – " + fmtT(u.scales.x.max);
    }
  }

  function options(spec, el, x) {
    var cats = spec.categories;
    var series = [{ label: "time", value: function (u, v) { return fmtT(v); } }];
    spec.series.forEach(function (s) {
      series.push({
        label: s.label,
        stroke: s.color,
        width: s.width || 1.4,
        dash: s.dash ? [6, 4] : undefined,
        paths: s.step ? uPlot.paths.stepped({ align: 1 }) : undefined,
        points: { show: false },
        spanGaps: false,
        value: valueFmt(spec, s)
      });
    });
    var y = { auto: true };
    if (cats) { y = { auto: false, range: [-0.6, cats.length - 0.4] }; }
    else if (spec.yRange) { y = { auto: false, range: spec.yRange }; }
    var yAxis = { size: cats ? 110 : 64, label: spec.unit || "", labelSize: 18 };
    if (cats) {
      yAxis.splits = function () { return cats.map(function (_, i) { return i; }); };
      yAxis.values = function (u, vals) { return vals.map(function (v) { return cats[v] || ""; }); };
    } else {
      yAxis.values = function (u, vals) { return vals.map(fmtNum); };
    }
    return {
      width: Math.max(240, el.clientWidth),
      height: spec.height,
      scales: { x: { time: false, range: function (u, min, max) { return [min, max]; } }, y: y },
      axes: [{ incrs: TIME_INCRS, values: function (u, vals) { return vals.map(fmtTick); } }, yAxis],
      series: series,
      cursor: { sync: { key: spec.group }, drag: { x: true, y: false, setScale: true } },
      legend: { live: true },
      plugins: [shade(spec), wheelZoom(x[0], x[x.length - 1])],
      hooks: { setScale: [onScale] }
    };
  }

  function draw(el) {
    if (el.getAttribute("data-state")) { return Promise.resolve(); }
    el.setAttribute("data-state", "loading");
    var spec = DATA.charts[el.getAttribute("data-chart")];
    var keys = [spec.x || DATA.t].concat(spec.series.map(function (s) { return s.key; }));
    return Promise.all(keys.map(decode)).then(function (arrays) {
      var x = arrays[0];
      var data = [x];
      spec.series.forEach(function (s, i) {
        var src = arrays[i + 1], off = s.offset || 0, sc = s.scale || 1;
        data.push(off === 0 && sc === 1 ? src : src.map(function (v) { return v == null ? null : v * sc + off; }));
      });
      var u = new uPlot(options(spec, el, x), data, el.querySelector(".plot"));
      u.ppGroup = spec.group;
      u.ppX = [x[0], x[x.length - 1]];
      u.ppReady = true;
      (groups[spec.group] = groups[spec.group] || []).push(u);
      var z = zoomed[spec.group];
      if (z) { u.setScale("x", { min: z[0], max: z[1] }); }  // join a group already zoomed in
      charts[spec.id] = u;
      el.setAttribute("data-state", "drawn");
      drawn++;
      document.body.setAttribute("data-charts", drawn + "/" + total);
    }).catch(function (err) {
      el.setAttribute("data-state", "error");
      el.querySelector(".plot").textContent = "This chart could not be drawn here (" + err + ").";
    });
  }

  function visible(el) {
    for (var p = el.parentElement; p; p = p.parentElement) {
      if (p.tagName === "DETAILS" && !p.open) { return false; }
    }
    return true;
  }

  function start() {
    var els = document.querySelectorAll(".chart[data-chart]");
    total = els.length;
    document.body.setAttribute("data-charts", "0/" + total);
    if (typeof DecompressionStream === "undefined") {
      els.forEach(function (el) {
        el.querySelector(".plot").textContent = "This browser cannot unpack the chart data (it"
          + " lacks DecompressionStream); the tables above hold the figures.";
      });
      return;
    }
    var first = [];
    els.forEach(function (el) { if (visible(el)) { first.push(draw(el)); } });
    Promise.all(first).then(function () { document.body.setAttribute("data-ready", "1"); });
    document.querySelectorAll("details").forEach(function (d) {
      d.addEventListener("toggle", function () {
        if (d.open) { d.querySelectorAll(".chart[data-chart]").forEach(function (el) { draw(el); }); }
      });
    });
    document.querySelectorAll("button[data-reset]").forEach(function (b) {
      b.addEventListener("click", function () {
        var g = groups[b.getAttribute("data-reset")] || [];
        if (g.length) { g[0].setScale("x", { min: g[0].ppX[0], max: g[0].ppX[1] }); }
      });
    });
    var pending = null;
    window.addEventListener("resize", function () {
      clearTimeout(pending);
      pending = setTimeout(function () {
        Object.keys(charts).forEach(function (id) {
          var u = charts[id], el = u.root.parentElement.parentElement;
          u.setSize({ width: Math.max(240, el.clientWidth), height: u.height });
        });
      }, 150);
    });
  }

  if (document.readyState === "loading") { document.addEventListener("DOMContentLoaded", start); }
  else { start(); }
})();
