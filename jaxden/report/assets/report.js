// jaxden report: decodes the linear pixels embedded in the page, tone maps them at the chosen
// exposure (the same transform as jaxden.report.tonemap.tonemap), colour maps the error
// maps, and draws every view of a scene with one shared zoom and pan. Plain JavaScript, no
// libraries, nothing fetched.
(function () {
  "use strict";
  const DATA = JSON.parse(document.getElementById("jaxden-data").textContent);
  const statusBox = document.querySelector('[data-out="status"]');

  // float16 bit pattern -> float32, as a table (65536 entries)
  const HALF = new Float32Array(65536);
  for (let h = 0; h < 65536; h++) {
    const sign = h & 0x8000 ? -1 : 1, e = (h >> 10) & 0x1f, m = h & 0x3ff;
    HALF[h] = sign * (e === 0 ? m * Math.pow(2, -24)
      : e === 31 ? (m ? NaN : Infinity) : (1 + m / 1024) * Math.pow(2, e - 15));
  }

  function base64Bytes(text) {
    const binary = atob(text), bytes = new Uint8Array(binary.length);
    for (let i = 0; i < binary.length; i++) bytes[i] = binary.charCodeAt(i);
    return bytes;
  }

  async function decodeArray(blob) {
    const stream = new Blob([base64Bytes(blob.data)]).stream()
      .pipeThrough(new DecompressionStream("deflate"));
    const buffer = await new Response(stream).arrayBuffer();
    let values;
    if (blob.dtype === "f16") {
      const bits = new Uint16Array(buffer);
      values = new Float32Array(bits.length);
      for (let i = 0; i < bits.length; i++) values[i] = HALF[bits[i]];
    } else {
      values = new Float32Array(buffer);
    }
    const shape = blob.shape;
    return { h: shape[0], w: shape[1], c: shape.length > 2 ? shape[2] : 1, values: values };
  }

  const COLORMAPS = {};
  for (const name in DATA.colormaps) COLORMAPS[name] = base64Bytes(DATA.colormaps[name]);

  function srgb(v) {
    if (!(v > 0)) return 0;
    if (v >= 1) return 1;
    return v <= 0.0031308 ? 12.92 * v : 1.055 * Math.pow(v, 1 / 2.4) - 0.055;
  }

  function mapPosition(v, layer) {
    let low = layer.low, high = layer.high;
    if (!(v === v)) v = 0;
    if (layer.scale === "log") {
      v = Math.log10(Math.max(v, low * 1e-3));
      low = Math.log10(low);
      high = Math.log10(high);
    }
    return Math.min(1, Math.max(0, (v - low) / (high - low)));
  }

  // An offscreen canvas holding a source's display pixels (RGBA, one per image pixel).
  function paint(source, scene, layerName, stops) {
    const stamp = layerName === "image" ? stops : "map";
    if (source.stamp === stamp) return source.canvas;
    if (!source.canvas) {
      source.canvas = document.createElement("canvas");
      source.canvas.width = source.w;
      source.canvas.height = source.h;
    }
    const ctx = source.canvas.getContext("2d");
    const image = ctx.createImageData(source.w, source.h), out = image.data;
    const n = source.w * source.h, c = source.c, v = source.values;
    if (layerName === "image") {
      const scale = Math.pow(2, stops);
      for (let i = 0; i < n; i++) {
        for (let k = 0; k < 3; k++) {
          out[4 * i + k] = Math.round(255 * srgb(v[i * c + (c === 1 ? 0 : k)] * scale));
        }
        out[4 * i + 3] = 255;
      }
    } else {
      const layer = scene.layers[layerName], table = COLORMAPS[layer.colormap];
      for (let i = 0; i < n; i++) {
        const index = Math.round(255 * mapPosition(v[i], layer));
        out[4 * i] = table[3 * index];
        out[4 * i + 1] = table[3 * index + 1];
        out[4 * i + 2] = table[3 * index + 2];
        out[4 * i + 3] = 255;
      }
    }
    ctx.putImageData(image, 0, 0);
    source.stamp = stamp;
    return source.canvas;
  }

  function key(layer, method, spp) {
    if (layer === "image") return method === "reference" ? "reference" : spp + "/" + method;
    return layer + "/" + spp + "/" + method;
  }

  function formatValue(x) {
    if (x === undefined || x === null) return "–";
    const a = Math.abs(x);
    return a !== 0 && (a < 1e-3 || a >= 1e4) ? x.toExponential(3) : x.toPrecision(4);
  }

  class SceneView {
    constructor(section, scene) {
      this.section = section;
      this.scene = scene;
      this.sources = {};
      this.controls = {};
      section.querySelectorAll("[data-control]").forEach((el) => {
        this.controls[el.dataset.control] = el;
      });
      this.state = { spp: Number(this.controls.spp.value), a: this.controls.a.value,
                     b: this.controls.b.value, layer: this.controls.layer.value,
                     stops: Number(this.controls.stops.value), split: 0.5 };
      this.resetView();
      this.views = Array.from(section.querySelectorAll("canvas.view"));
      const ratio = window.devicePixelRatio || 1;
      for (const canvas of this.views) {
        canvas.width = Math.round(canvas.clientWidth * ratio);
        canvas.height = Math.round(canvas.clientHeight * ratio);
      }
    }

    async load() {
      const entries = Object.entries(this.scene.arrays);
      const decoded = await Promise.all(entries.map(([, blob]) => decodeArray(blob)));
      entries.forEach(([name], i) => { this.sources[name] = decoded[i]; });
    }

    resetView() {
      this.zoom = 1;
      this.cx = this.scene.width / 2;
      this.cy = this.scene.height / 2;
    }

    scale(canvas) {
      return Math.min(canvas.width / this.scene.width, canvas.height / this.scene.height)
        * this.zoom;
    }

    // canvas pixel of an event -> image coordinates
    imagePoint(canvas, event) {
      const rect = canvas.getBoundingClientRect();
      const px = (event.clientX - rect.left) * canvas.width / rect.width;
      const py = (event.clientY - rect.top) * canvas.height / rect.height;
      const s = this.scale(canvas);
      return { px: px, py: py, x: (px - canvas.width / 2) / s + this.cx,
               y: (py - canvas.height / 2) / s + this.cy };
    }

    blit(ctx, canvas, layer, method) {
      const source = this.sources[key(layer, method, this.state.spp)];
      if (!source) {
        ctx.fillStyle = "#999";
        ctx.font = Math.round(11 * (window.devicePixelRatio || 1)) + "px sans-serif";
        ctx.fillText(method === "reference" ? "(reference: no error)" : "(none at this spp)",
                     8, canvas.height / 2);
        return;
      }
      const s = this.scale(canvas);
      ctx.save();
      ctx.imageSmoothingEnabled = false;
      ctx.setTransform(s, 0, 0, s, canvas.width / 2 - this.cx * s,
                       canvas.height / 2 - this.cy * s);
      ctx.drawImage(paint(source, this.scene, layer, this.state.stops), 0, 0);
      ctx.restore();
    }

    drawView(canvas) {
      const ctx = canvas.getContext("2d");
      ctx.fillStyle = "#2b2b2b";
      ctx.fillRect(0, 0, canvas.width, canvas.height);
      if (canvas.dataset.role === "panel") {
        this.blit(ctx, canvas, canvas.dataset.layer, canvas.dataset.method);
        return;
      }
      const split = Math.round(this.state.split * canvas.width);
      for (const [side, x0, x1] of [["a", 0, split], ["b", split, canvas.width]]) {
        ctx.save();
        ctx.beginPath();
        ctx.rect(x0, 0, x1 - x0, canvas.height);
        ctx.clip();
        this.blit(ctx, canvas, this.state.layer, this.state[side]);
        ctx.restore();
      }
      ctx.fillStyle = "rgba(255,255,255,0.9)";
      ctx.fillRect(split - 1, 0, 2, canvas.height);
    }

    draw() {
      for (const canvas of this.views) this.drawView(canvas);
    }

    row(method) {
      return this.scene.rows.find((r) => r.spp === this.state.spp && r.method === method);
    }

    updateLabels() {
      const st = this.state;
      this.section.querySelectorAll('[data-out="spp"]').forEach((el) => {
        el.textContent = st.spp;
      });
      this.section.querySelector('[data-out="a"]').textContent = "A: " + st.a;
      this.section.querySelector('[data-out="b"]').textContent = "B: " + st.b;
      const sign = st.stops >= 0 ? "+" : "";
      this.section.querySelector('[data-out="stops"]').textContent =
        sign + st.stops.toFixed(1) + " stops (×" + formatValue(Math.pow(2, st.stops)) + ")";
      this.section.querySelectorAll("figcaption[data-caption]").forEach((el) => {
        const method = el.dataset.caption;
        const layer = el.previousElementSibling.dataset.layer;
        const r = this.row(method);
        let text = method;
        if (r && layer === "image") {
          text += " · relMSE " + formatValue(r.relmse) + " · FLIP " + formatValue(r.flip);
        } else if (r && layer === "relse") {
          text += " · relMSE " + formatValue(r.relmse);
        } else if (r && layer === "flip") {
          text += " · FLIP " + formatValue(r.flip);
        }
        el.textContent = text;
      });
    }

    readout(point) {
      const x = Math.floor(point.x), y = Math.floor(point.y), sc = this.scene;
      const box = this.section.querySelector('[data-out="readout"]');
      if (x < 0 || y < 0 || x >= sc.width || y >= sc.height) {
        box.textContent = "hover over an image for its values";
        return;
      }
      const lines = ["pixel (" + x * sc.factor + ", " + y * sc.factor + ")"];
      const seen = new Set();
      for (const method of [this.state.a, this.state.b, "reference"]) {
        if (seen.has(method)) continue;
        seen.add(method);
        const image = this.sources[key("image", method, this.state.spp)];
        if (!image) continue;
        const at = (y * image.w + x) * image.c;
        let text = method.padEnd(12) + " RGB " +
          [0, 1, 2].map((k) => formatValue(image.values[at + k])).join(" ");
        for (const layer of ["relse", "flip", "alpha"]) {
          const map = this.sources[key(layer, method, this.state.spp)];
          if (map) text += "  " + layer + " " + formatValue(map.values[y * map.w + x]);
        }
        lines.push(text);
      }
      box.textContent = lines.join("\n");
    }

    attach() {
      const c = this.controls;
      for (const name of ["spp", "a", "b", "layer"]) {
        c[name].addEventListener("change", () => {
          this.state[name] = name === "spp" ? Number(c[name].value) : c[name].value;
          this.updateLabels();
          this.draw();
        });
      }
      c.stops.addEventListener("input", () => {
        this.state.stops = Number(c.stops.value);
        this.updateLabels();
        this.draw();
      });
      c.split.addEventListener("input", () => {
        this.state.split = Number(c.split.value) / 1000;
        this.drawView(this.views.find((v) => v.dataset.role === "compare"));
      });
      this.section.querySelector('[data-action="auto"]').addEventListener("click", () => {
        c.stops.value = this.scene.stops;
        c.stops.dispatchEvent(new Event("input"));
      });
      this.section.querySelector('[data-action="reset"]').addEventListener("click", () => {
        this.resetView();
        this.draw();
      });
      for (const canvas of this.views) this.attachView(canvas);
    }

    attachView(canvas) {
      canvas.addEventListener("wheel", (event) => {
        event.preventDefault();
        const p = this.imagePoint(canvas, event);
        const factor = Math.exp(-event.deltaY * (event.deltaMode === 1 ? 0.05 : 0.0015));
        this.zoom = Math.min(256, Math.max(0.25, this.zoom * factor));
        const s = this.scale(canvas);  // keep the point under the cursor in place
        this.cx = p.x - (p.px - canvas.width / 2) / s;
        this.cy = p.y - (p.py - canvas.height / 2) / s;
        this.draw();
      }, { passive: false });
      let drag = null;
      canvas.addEventListener("pointerdown", (event) => {
        drag = { x: event.clientX, y: event.clientY };
        canvas.setPointerCapture(event.pointerId);
      });
      canvas.addEventListener("pointermove", (event) => {
        if (drag) {
          const rect = canvas.getBoundingClientRect(), s = this.scale(canvas);
          this.cx -= (event.clientX - drag.x) * canvas.width / rect.width / s;
          this.cy -= (event.clientY - drag.y) * canvas.height / rect.height / s;
          drag = { x: event.clientX, y: event.clientY };
          this.draw();
        }
        this.readout(this.imagePoint(canvas, event));
      });
      const end = () => { drag = null; };
      canvas.addEventListener("pointerup", end);
      canvas.addEventListener("pointercancel", end);
      canvas.addEventListener("dblclick", () => {
        this.resetView();
        this.draw();
      });
    }
  }

  function drawColourBars(section, scene) {
    section.querySelectorAll("canvas[data-colorbar]").forEach((canvas) => {
      const layer = scene.layers[canvas.dataset.colorbar], table = COLORMAPS[layer.colormap];
      const ctx = canvas.getContext("2d"), image = ctx.createImageData(256, canvas.height);
      for (let y = 0; y < canvas.height; y++) {
        for (let x = 0; x < 256; x++) {
          const o = 4 * (y * 256 + x);
          image.data[o] = table[3 * x];
          image.data[o + 1] = table[3 * x + 1];
          image.data[o + 2] = table[3 * x + 2];
          image.data[o + 3] = 255;
        }
      }
      ctx.putImageData(image, 0, 0);
    });
  }

  const views = [];
  async function main() {
    for (const section of document.querySelectorAll("section.scene")) {
      const scene = DATA.scenes[Number(section.dataset.scene)];
      const view = new SceneView(section, scene);
      views.push(view);
      await view.load();
      drawColourBars(section, scene);
      view.attach();
      view.updateLabels();
      view.draw();
    }
    statusBox.textContent = "";
    document.documentElement.dataset.ready = "true";
  }

  // For tests and the curious: the views, and the display pixels of a source.
  window.jaxdenReport = {
    views: views,
    pixels: function (sceneIndex, name) {
      const view = views[sceneIndex], layer = name.includes("/") && isNaN(name[0])
        ? name.split("/")[0] : "image";
      const canvas = paint(view.sources[name], view.scene, layer, view.state.stops);
      const data = canvas.getContext("2d").getImageData(0, 0, canvas.width, canvas.height);
      return Array.from(data.data);
    },
    ready: main().catch((error) => {
      statusBox.textContent = "the report could not be shown: " + error;
      statusBox.classList.add("error");
      console.error(error);
      document.documentElement.dataset.ready = "error";
    }),
  };
})();
