// The panel, on three.js' lil-gui: per agent a row with its garments' colours, the frames per second reaching this
// page and the node's own numbers from its ~/status topic; body-shape sliders that publish on the chosen agent's
// body_shape topic (through the server). lil-gui's styles come as a file (lil-gui.css, served from the module's own
// text) instead of the <style> it would inject: the page's Content-Security-Policy allows style sheets of its origin
// only.
import GUI from 'three/addons/libs/lil-gui.module.min.js';

function css(color) {
  return `rgb(${color.map((c) => Math.round(255 * c)).join(',')})`;
}

export class Panel {
  constructor(onShape) {
    this.onShape = onShape;
    this.gui = new GUI({ title: 'agentdress · connecting', injectStyles: false, width: 320 });
    this.gui.domElement.id = 'panel';
    this.agentsFolder = this.gui.addFolder('agents');
    this.agentsFolder.domElement.id = 'agents';
    this.shapeFolder = this.gui.addFolder('body shape');
    this.shapeFolder.domElement.id = 'sliders';
    // agent -> {row (a lil-gui controller), line: {text}, keys: Map(mesh key -> garment colour)}
    this.agents = new Map();
    this.meshFps = {}; // mesh key -> frames per second reaching the page (counted by the socket worker)
    this.status = new Map(); // status source (a node name) -> status JSON
    this.phenotypes = [];
    this.values = {}; // agent -> the slider values last sent
    this.shape = { agent: '' }; // what the shape controllers show: the chosen agent and one value per phenotype
    this.sliders = [];
    this.timer = null;
  }

  setConnection(text) { this.gui.title(`agentdress · ${text}`); }

  agent(name) {
    let entry = this.agents.get(name);
    if (!entry) {
      const line = { text: '' };
      const row = this.agentsFolder.add(line, 'text').disable();
      row.domElement.dataset.agent = name;
      entry = { row, line, keys: new Map() };
      this.agents.set(name, entry);
      this.buildShape();
    }
    return entry;
  }

  addMesh(header) {
    this.agent(header.agent).keys.set(header.key, header.color);
  }

  // A mesh is gone: its swatch leaves its own agent's row only, and an agent without meshes leaves the panel.
  removeMesh(key) {
    for (const [name, entry] of this.agents) {
      if (!entry.keys.delete(key) || entry.keys.size) continue;
      entry.row.destroy();
      this.agents.delete(name);
      delete this.values[name];
      this.buildShape();
    }
  }

  setMeshFps(fps) { this.meshFps = fps; }

  setStatus(source, status) {
    this.status.set(source, status);
    // sliders shown before the node said its shape start at the node's shape once it does (untouched ones only)
    const agent = this.shape.agent;
    if (agent && !this.slidersFromStatus && !this.values[agent]) this.showShape();
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
    this.buildShape();
  }

  // The agent choice and one slider per phenotype, made again when agents come or go (lil-gui's options cannot
  // change in place).
  buildShape() {
    for (const controller of [...this.shapeFolder.controllers]) controller.destroy();
    this.sliders = [];
    const names = [...this.agents.keys()];
    if (!names.includes(this.shape.agent)) this.shape.agent = names[0] || '';
    if (!names.length || !this.phenotypes.length) return;
    this.shapeFolder.add(this.shape, 'agent', names).onChange(() => this.showShape());
    this.sliders = this.phenotypes.map((name) => {
      this.shape[name] ??= 0.5; // lil-gui controls existing properties only; showShape sets the real values
      const slider = this.shapeFolder.add(this.shape, name, 0, 1, 0.01).onChange(() => this.shapeChanged());
      slider.$input.name = name; // found by name (tests, scripts)
      return slider;
    });
    this.showShape();
  }

  // The chosen agent's values: those last sent from here, else the node's, else the middle of every range.
  showShape() {
    const agent = this.shape.agent;
    const status = this.statusOf(agent);
    this.slidersFromStatus = Boolean(status && status.shape);
    const values = this.values[agent] || (status && status.shape) || this.phenotypes.map(() => 0.5);
    this.phenotypes.forEach((name, i) => { this.shape[name] = Number(values[i]); });
    for (const slider of this.sliders) slider.updateDisplay(); // updateDisplay, not setValue: nothing is sent
  }

  shapeChanged() {
    const agent = this.shape.agent;
    const values = this.phenotypes.map((name) => Number(this.shape[name]));
    this.values[agent] = values;
    clearTimeout(this.timer); // a drag sends at most ~10 shapes per second: each one refits the garments
    this.timer = setTimeout(() => this.onShape(agent, values), 100);
  }

  // Called once per rendered frame: refreshes the rows about 4 times a second and returns {agent: frames per
  // second received}, an agent's rate being that of its most frequent mesh (its garments arrive one by one).
  update(now) {
    const fps = {};
    for (const [name, entry] of this.agents) {
      fps[name] = Math.max(0, ...[...entry.keys.keys()].map((key) => this.meshFps[key] || 0));
    }
    if (!this.lastDraw || now - this.lastDraw > 250) {
      this.lastDraw = now;
      for (const [name, entry] of this.agents) {
        const status = this.statusOf(name);
        let text = `${fps[name].toFixed(0)} fps in`;
        if (status) {
          const synth = status.synthesis_ms ? status.synthesis_ms.p50 : undefined;
          if (status.tick_rate_hz !== undefined) text += ` · node ${Number(status.tick_rate_hz).toFixed(0)} Hz`;
          if (synth !== undefined) text += ` · ${Number(synth).toFixed(2)} ms`;
        }
        entry.line.text = text;
        entry.row.updateDisplay();
        // the name with one swatch per garment; colours through the CSSOM (no inline style attributes)
        const swatches = [...entry.keys.values()].map((color) => {
          const swatch = document.createElement('span');
          swatch.className = 'swatch';
          swatch.style.background = css(color);
          return swatch;
        });
        entry.row.$name.replaceChildren(...swatches, name);
        entry.row.$name.title = name;
      }
    }
    return fps;
  }
}
