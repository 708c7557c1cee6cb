// The small panel: per agent the frames per second reaching this page and the node's own numbers from its
// ~/status topic; body-shape sliders that publish on the chosen agent's body_shape topic (through the server).
function css(color) {
  return `rgb(${color.map((c) => Math.round(255 * c)).join(',')})`;
}

export class Panel {
  constructor(root, onShape) {
    this.root = root;
    this.onShape = onShape;
    this.agents = new Map(); // agent -> {row, keys: Set(mesh key), garments: Map(garment -> color)}
    this.meshFps = {}; // mesh key -> frames per second reaching the page (counted by the socket worker)
    this.status = new Map(); // status source (a node name) -> status JSON
    this.phenotypes = [];
    this.values = {}; // agent -> the slider values last sent
    this.select = root.querySelector('#shape-agent');
    this.sliders = root.querySelector('#sliders');
    this.select.addEventListener('change', () => this.buildSliders());
    this.timer = null;
  }

  setConnection(text) { this.root.querySelector('#connection').textContent = text; }

  agent(name) {
    let entry = this.agents.get(name);
    if (!entry) {
      const row = document.createElement('div');
      row.className = 'agent';
      this.root.querySelector('#agents').appendChild(row);
      entry = { row, keys: new Set(), garments: new Map() };
      this.agents.set(name, entry);
      const option = document.createElement('option');
      option.value = option.textContent = name;
      this.select.appendChild(option);
      if (this.agents.size === 1) this.buildSliders();
    }
    return entry;
  }

  addMesh(header) {
    const entry = this.agent(header.agent);
    entry.garments.set(header.garment, header.color);
    entry.keys.add(header.key);
  }

  removeMesh(key) {
    for (const entry of this.agents.values()) {
      entry.garments.delete(key.split('/').pop());
      entry.keys.delete(key);
    }
  }

  setMeshFps(fps) { this.meshFps = fps; }

  setStatus(source, status) {
    this.status.set(source, status);
    // sliders drawn before the node said its shape start at the node's shape once it does (untouched ones only)
    const agent = this.select.value;
    if (agent && !this.slidersFromStatus && !this.values[agent]) this.buildSliders();
  }

  // The node status that speaks for an agent: its own node's, or the crowd node's entry for it.
  statusOf(agent) {
    for (const [source, status] of this.status) {
      const node = String(source).replace(/^\//, '');
      if (agent === node) return status;
      if (agent.startsWith(node + '/')) {
        const detail = (status.agents_detail || {})[agent.slice(node.length + 1)];
        return Object.assign({}, status, detail || {});
      }
    }
    return null;
  }

  setPhenotypes(names) {
    this.phenotypes = names;
    this.buildSliders();
  }

  buildSliders() {
    const agent = this.select.value;
    this.sliders.textContent = '';
    if (!agent || !this.phenotypes.length) return;
    const status = this.statusOf(agent);
    this.slidersFromStatus = Boolean(status && status.shape);
    const values = this.values[agent] || (status && status.shape) || this.phenotypes.map(() => 0.5);
    this.phenotypes.forEach((name, i) => {
      const label = document.createElement('label');
      const input = document.createElement('input');
      const shown = document.createElement('span');
      Object.assign(input, { type: 'range', min: 0, max: 1, step: 0.01, value: values[i], name });
      shown.textContent = Number(values[i]).toFixed(2);
      input.addEventListener('input', () => {
        shown.textContent = Number(input.value).toFixed(2);
        this.shapeChanged(agent);
      });
      label.append(name, input, shown);
      this.sliders.appendChild(label);
    });
  }

  shapeChanged(agent) {
    const values = [...this.sliders.querySelectorAll('input')].map((input) => Number(input.value));
    this.values[agent] = values;
    clearTimeout(this.timer); // a drag sends at most ~10 shapes per second: each one refits the garments
    this.timer = setTimeout(() => this.onShape(agent, values), 100);
  }

  // Called once per rendered frame: refreshes the rows about 4 times a second and returns {agent: frames per
  // second received}, an agent's rate being that of its most frequent mesh (its garments arrive one by one).
  update(now) {
    const fps = {};
    for (const [name, entry] of this.agents) {
      fps[name] = Math.max(0, ...[...entry.keys].map((key) => this.meshFps[key] || 0));
    }
    if (!this.lastDraw || now - this.lastDraw > 250) {
      this.lastDraw = now;
      for (const [name, entry] of this.agents) {
        const status = this.statusOf(name);
        // nodes built here, colours set through the CSSOM: the page's policy allows no inline style attributes
        const swatches = [...entry.garments.values()].map((c) => {
          const swatch = document.createElement('span');
          swatch.className = 'swatch';
          swatch.style.background = css(c);
          return swatch;
        });
        const bold = document.createElement('b');
        bold.textContent = name;
        let text = ` ${fps[name].toFixed(0)} fps in`;
        if (status) {
          const synth = status.synthesis_ms ? status.synthesis_ms.p50 : undefined;
          if (status.tick_rate_hz !== undefined) text += ` · node ${Number(status.tick_rate_hz).toFixed(0)} Hz`;
          if (synth !== undefined) text += ` · ${Number(synth).toFixed(2)} ms`;
        }
        entry.row.replaceChildren(...swatches, bold, text);
      }
    }
    return fps;
  }
}
