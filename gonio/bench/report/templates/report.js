/* gonio report: the one script of the page (allowed by its hash in the Content-Security-Policy).
   1. After load, record how many images the browser decoded (the headless-browser test reads it).
   2. The interactive view: the measured points and the fitted lobe of one incidence, in 3-D on a
      canvas (drag to turn, select the incidence and channel). Data from the JSON element
      #view-data, parsed, never evaluated; text goes to the page only as textContent. */
(function () {
  'use strict';
  window.addEventListener('load', function () {
    var im = Array.prototype.slice.call(document.images);
    document.body.setAttribute('data-images-decoded',
      im.filter(function (i) { return i.complete && i.naturalWidth > 0; }).length + '/' + im.length);
  });
  var holder = document.getElementById('view-data');
  var canvas = document.getElementById('view-canvas');
  if (!holder || !canvas || !canvas.getContext) { return; }
  var data;
  try { data = JSON.parse(holder.textContent); } catch (e) { return; }
  var ctx = canvas.getContext('2d');
  var selInc = document.getElementById('view-incidence');
  var selCh = document.getElementById('view-channel');
  var logBox = document.getElementById('view-log');
  var info = document.getElementById('view-info');
  var D = Math.PI / 180;
  var yaw = -35 * D, pitch = 25 * D, projected = [];
  data.incidences.forEach(function (g, k) {
    var o = document.createElement('option');
    o.value = String(k);
    o.textContent = 'theta_i ' + g.theta_i.toFixed(0) + ' deg, phi_i ' + g.phi_i.toFixed(0) + ' deg (' + g.points.length + ' points)';
    selInc.appendChild(o);
  });
  data.channels.forEach(function (c, k) {
    var o = document.createElement('option');
    o.value = String(k);
    o.textContent = c;
    selCh.appendChild(o);
  });
  if (data.channels.length > 1) { selCh.value = '1'; }
  var most = 0;
  data.incidences.forEach(function (g, k) { if (g.points.length > data.incidences[most].points.length) { most = k; } });
  selInc.value = String(most);
  function dir(theta, phi) {
    return [Math.sin(theta * D) * Math.cos(phi * D), Math.sin(theta * D) * Math.sin(phi * D), Math.cos(theta * D)];
  }
  function project(v, scale) {
    var x = v[0] * Math.cos(yaw) - v[1] * Math.sin(yaw);
    var y = v[0] * Math.sin(yaw) + v[1] * Math.cos(yaw);
    var z = v[2];
    var y2 = y * Math.sin(pitch) + z * Math.cos(pitch);
    return [canvas.width / 2 + scale * x, canvas.height * 0.72 - scale * y2];
  }
  function draw() {
    var g = data.incidences[Number(selInc.value)];
    var c = Number(selCh.value);
    if (!g) { return; }
    var P = data.points, log = logBox.checked, vals = [];
    g.points.forEach(function (i) { if (P.f[c][i] > 0) { vals.push(P.f[c][i]); } });
    if (g.lobe) { g.lobe[c].forEach(function (v) { if (v > 0) { vals.push(v); } }); }
    var fmax = Math.max.apply(null, vals.concat([1e-12]));
    var fmin = Math.max(fmax * 1e-3, Math.min.apply(null, vals.concat([fmax])));
    function radius(f) {
      if (!(f > 0)) { return 0; }
      return log ? Math.max(0, Math.log(f / fmin) / Math.log(fmax / fmin)) : f / fmax;
    }
    var scale = Math.min(canvas.width, canvas.height) * 0.42;
    ctx.clearRect(0, 0, canvas.width, canvas.height);
    ctx.lineWidth = 1;
    ctx.strokeStyle = '#bbb';
    ctx.beginPath();
    for (var a = 0; a <= 360; a += 5) {
      var q = project(dir(90, a), scale);
      if (a === 0) { ctx.moveTo(q[0], q[1]); } else { ctx.lineTo(q[0], q[1]); }
    }
    ctx.stroke();
    var wi = dir(g.theta_i, g.phi_i), o0 = project([0, 0, 0], scale), qi = project(wi, scale);
    ctx.strokeStyle = '#e0a000';
    ctx.beginPath(); ctx.moveTo(o0[0], o0[1]); ctx.lineTo(qi[0], qi[1]); ctx.stroke();
    if (g.lobe) {
      var T = data.theta_o_grid, F = data.phi_o_grid, L = g.lobe[c];
      ctx.strokeStyle = 'rgba(40, 90, 170, 0.55)';
      for (var pass = 0; pass < 2; pass++) {
        var outer = pass === 0 ? T.length : F.length, inner = pass === 0 ? F.length : T.length;
        for (var u = 0; u < outer; u++) {
          ctx.beginPath();
          for (var w = 0; w < inner; w++) {
            var ti = pass === 0 ? u : w, pj = pass === 0 ? w : u;
            var v = dir(T[ti], F[pj]), r = radius(L[ti * F.length + pj]);
            var q2 = project([v[0] * r, v[1] * r, v[2] * r], scale);
            if (w === 0) { ctx.moveTo(q2[0], q2[1]); } else { ctx.lineTo(q2[0], q2[1]); }
          }
          ctx.stroke();
        }
      }
    }
    projected = [];
    ctx.fillStyle = '#c0392b';
    g.points.forEach(function (i) {
      var v = dir(P.theta_o[i], P.phi_o[i]), r = radius(P.f[c][i]);
      var q3 = project([v[0] * r, v[1] * r, v[2] * r], scale);
      projected.push([q3[0], q3[1], i]);
      ctx.beginPath(); ctx.arc(q3[0], q3[1], 3.5, 0, 2 * Math.PI); ctx.fill();
    });
    info.textContent = (g.lobe ? 'Blue mesh: the fit; ' : 'No fit: ') + 'red dots: measured, ' +
      (log ? 'radius log f_r over three decades' : 'radius proportional to f_r') + '; orange: the incidence. Drag to turn.';
  }
  var dragging = null;
  canvas.addEventListener('pointerdown', function (e) { dragging = [e.clientX, e.clientY]; canvas.setPointerCapture(e.pointerId); });
  canvas.addEventListener('pointerup', function () { dragging = null; });
  canvas.addEventListener('pointermove', function (e) {
    if (dragging) {
      yaw += (e.clientX - dragging[0]) * 0.01;
      pitch = Math.max(-1.5, Math.min(1.5, pitch + (e.clientY - dragging[1]) * 0.01));
      dragging = [e.clientX, e.clientY];
      draw();
      return;
    }
    var box = canvas.getBoundingClientRect();
    var x = (e.clientX - box.left) * canvas.width / box.width, y = (e.clientY - box.top) * canvas.height / box.height;
    var best = null, dist = 64;
    projected.forEach(function (p) {
      var d2 = (p[0] - x) * (p[0] - x) + (p[1] - y) * (p[1] - y);
      if (d2 < dist) { dist = d2; best = p[2]; }
    });
    if (best !== null) {
      var P = data.points, c = Number(selCh.value);
      info.textContent = 'point ' + best + ': theta_o ' + P.theta_o[best] + ' deg, phi_o ' + P.phi_o[best] +
        ' deg, f_r ' + P.f[c][best] + ' +- ' + P.u[c][best] + ' 1/sr';
    }
  });
  [selInc, selCh, logBox].forEach(function (el) { el.addEventListener('change', draw); });
  document.getElementById('view').removeAttribute('hidden');
  draw();
}());
