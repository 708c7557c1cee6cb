// The viewer's-eye check (agentdress_ros/evaluate/look.py), loaded only when the page's URL asks for it (?look=1).
// It draws the page's own meshes - the body as the page skins it, the garments as received - off screen at a fixed
// size, from views around the agent, in flat ID colours (no lighting, no antialiasing), and hands the pictures to
// the script that drives the page:
//   window.agentdressLook.setWholeBody(faces)  every body face (F*3 vertex ids): the reference pass draws the body
//                                              whole, on the same skinned vertices and bones as the shown one
//   window.agentdressLook.hide(faces)          leave these body faces out of the shown body too (a hole on purpose)
//   window.agentdressLook.stamps()             {mesh key: stamp of its last frame}
//   window.agentdressLook.capture(views, size) per view {shown, reference: base64 class per pixel (0 background,
//     1 body, 2.. garments in `classes` order), depth: base64 RGBA of the shown pass' depth (three's RGBA packing of
//     the window depth), unproject: 16 numbers, column-major: window (x, y, depth) in [-1, 1]^3 -> the node's
//     Z-up metres}, plus classes [mesh keys], garments {key: {positions, faces}} (the drawn garments).
// Pixels are rows bottom up (WebGL's readPixels order).
const NEAR = 0.1; // fixed near and far planes (metres) of every view
const FAR = 20.0;
const FOV = 30.0; // vertical field of view, degrees
const FILL = 0.9; // the agent's bounding box fills this share of the image's larger extent

export function install({ THREE, renderer, scene, world, meshes, stats }) {
  let wholeFaces = null;
  let hidden = null; // Set of "a,b,c" sorted vertex ids left out of the shown body
  let reference = null; // {source: the body mesh it copies, mesh: the whole body}
  let shownBody = null; // {source, index: the shown index with `hidden` left out}

  function bodyEntry() {
    for (const entry of meshes.values()) if (entry.garment === 'body') return entry;
    return null;
  }

  function twin(source, index) { // the same skinned vertices and bones, another index
    const geometry = new THREE.BufferGeometry();
    for (const name of ['position', 'skinIndex', 'skinWeight']) {
      const attribute = source.geometry.getAttribute(name);
      if (attribute) geometry.setAttribute(name, attribute);
    }
    geometry.setIndex(new THREE.BufferAttribute(index, 1));
    const mesh = source.isSkinnedMesh ? new THREE.SkinnedMesh(geometry, source.material) : new THREE.Mesh(geometry);
    if (source.isSkinnedMesh) {
      mesh.bindMode = source.bindMode;
      mesh.bind(source.skeleton, source.bindMatrix);
    }
    mesh.frustumCulled = false;
    mesh.visible = false;
    world.add(mesh);
    return mesh;
  }

  function drop(cache) {
    if (cache) { world.remove(cache.mesh); cache.mesh.geometry.dispose(); }
    return null;
  }

  function replaced(cache, source, make) {
    if (cache && cache.source === source) return cache;
    drop(cache);
    return { source, mesh: make() };
  }

  function bodies() {
    const entry = bodyEntry();
    if (!entry) return { shown: null, whole: null };
    const source = entry.mesh;
    if (wholeFaces) reference = replaced(reference, source, () => twin(source, new Uint32Array(wholeFaces)));
    let shown = source;
    if (hidden) {
      shownBody = replaced(shownBody, source, () => {
        const faces = source.geometry.index.array;
        const kept = [];
        for (let f = 0; f < faces.length; f += 3) {
          const key = [faces[f], faces[f + 1], faces[f + 2]].sort((a, b) => a - b).join(',');
          if (!hidden.has(key)) kept.push(faces[f], faces[f + 1], faces[f + 2]);
        }
        return twin(source, new Uint32Array(kept));
      });
      shown = shownBody.mesh;
    }
    return { shown, whole: reference ? reference.mesh : null };
  }

  function base64(bytes) {
    let text = '';
    for (let i = 0; i < bytes.length; i += 0x8000) {
      text += String.fromCharCode.apply(null, bytes.subarray(i, i + 0x8000));
    }
    return btoa(text);
  }

  function agentBox() {
    const box = new THREE.Box3();
    for (const { mesh } of meshes.values()) box.expandByObject(mesh, true);
    return box;
  }

  // A camera on `view` {azimuth, elevation (degrees, looking down) | height (metres above the feet, looking at the
  // centre)} around the agent, as near as lets the agent's box fill FILL of the image.
  function placeCamera(camera, view, box) {
    const centre = box.getCenter(new THREE.Vector3());
    const corners = [];
    for (const x of [box.min.x, box.max.x]) {
      for (const y of [box.min.y, box.max.y]) {
        for (const z of [box.min.z, box.max.z]) corners.push(new THREE.Vector3(x, y, z));
      }
    }
    const azimuth = THREE.MathUtils.degToRad(view.azimuth);
    let distance = 4.0;
    for (let round = 0; round < 6; round++) {
      let elevation = THREE.MathUtils.degToRad(view.elevation ?? 0);
      if (view.height !== undefined) elevation = Math.atan2(centre.y - (box.min.y + view.height), distance);
      const direction = new THREE.Vector3(Math.sin(azimuth) * Math.cos(elevation), Math.sin(elevation),
        Math.cos(azimuth) * Math.cos(elevation));
      camera.position.copy(centre).addScaledVector(direction, distance);
      camera.lookAt(centre);
      camera.updateMatrixWorld();
      let extent = 0;
      for (const corner of corners) {
        const p = corner.clone().project(camera);
        extent = Math.max(extent, Math.abs(p.x), Math.abs(p.y));
      }
      distance *= extent / FILL;
    }
  }

  function ids(classes) {
    const materials = new Map();
    classes.forEach((key, i) => {
      const entry = meshes.get(key);
      materials.set(key, new THREE.MeshBasicMaterial({ color: new THREE.Color((i + 1) / 255, 0, 0),
        side: entry.mesh.material.side, polygonOffset: entry.mesh.material.polygonOffset,
        polygonOffsetFactor: entry.mesh.material.polygonOffsetFactor,
        polygonOffsetUnits: entry.mesh.material.polygonOffsetUnits }));
    });
    return materials;
  }

  function capture(views, size = 512) {
    const entry = bodyEntry();
    const { shown, whole } = bodies();
    if (!entry || !whole) throw new Error('look: no body, or setWholeBody was not called');
    const keys = [...meshes.keys()];
    const classes = [entry.mesh.name, ...keys.filter((k) => meshes.get(k).garment !== 'body')];
    const idMaterials = ids(classes);
    const depthMaterials = new Map([...idMaterials].map(([key, m]) => [key, new THREE.MeshDepthMaterial({
      depthPacking: THREE.RGBADepthPacking, side: m.side, polygonOffset: m.polygonOffset,
      polygonOffsetFactor: m.polygonOffsetFactor, polygonOffsetUnits: m.polygonOffsetUnits })]));
    const target = new THREE.WebGLRenderTarget(size, size, { samples: 0 });
    const camera = new THREE.PerspectiveCamera(FOV, 1, NEAR, FAR);
    const saved = { background: scene.background, visible: new Map(), materials: new Map() };
    for (const child of scene.children) saved.visible.set(child, child.visible);
    for (const child of world.children) saved.visible.set(child, child.visible);
    for (const { mesh } of meshes.values()) saved.materials.set(mesh, mesh.material);
    const pixels = new Uint8Array(size * size * 4);
    const read = (channel) => {
      renderer.readRenderTargetPixels(target, 0, 0, size, size, pixels);
      if (!channel) return base64(pixels);
      const out = new Uint8Array(size * size);
      for (let i = 0; i < out.length; i++) out[i] = pixels[4 * i];
      return base64(out);
    };
    const draw = (body, materials) => {
      for (const child of scene.children) child.visible = child === world;
      for (const child of world.children) child.visible = false;
      for (const { mesh } of meshes.values()) {
        if (mesh !== entry.mesh) { mesh.visible = true; mesh.material = materials.get(mesh.name); }
      }
      body.visible = true;
      body.material = materials.get(entry.mesh.name);
      renderer.setRenderTarget(target);
      renderer.setClearColor(0x000000, 0);
      renderer.clear();
      renderer.render(scene, camera);
      renderer.setRenderTarget(null);
      body.visible = false;
    };
    const out = { classes, views: [], garments: {} };
    const xr = renderer.xr.enabled;
    renderer.xr.enabled = false;
    scene.background = null;
    try {
      const box = agentBox();
      for (const view of views) {
        placeCamera(camera, view, box);
        draw(shown, idMaterials);
        const shownIds = read(true);
        draw(shown, depthMaterials);
        const depth = read(false);
        draw(whole, idMaterials);
        const referenceIds = read(true);
        const unproject = new THREE.Matrix4().copy(world.matrixWorld).invert()
          .multiply(camera.matrixWorld).multiply(camera.projectionMatrixInverse);
        out.views.push({ view, shown: shownIds, reference: referenceIds, depth, unproject: unproject.toArray() });
      }
      for (const key of classes.slice(1)) {
        const mesh = meshes.get(key).mesh;
        out.garments[key] = { positions: stats.positions(key), faces: Array.from(mesh.geometry.index.array) };
      }
    } finally {
      renderer.xr.enabled = xr;
      scene.background = saved.background;
      for (const [object, visible] of saved.visible) object.visible = visible;
      for (const [mesh, material] of saved.materials) mesh.material = material;
      if (reference) reference.mesh.visible = false;
      if (shownBody) shownBody.mesh.visible = false;
      target.dispose();
      for (const m of [...idMaterials.values(), ...depthMaterials.values()]) m.dispose();
    }
    return out;
  }

  window.agentdressLook = {
    setWholeBody(faces) { wholeFaces = faces; reference = drop(reference); },
    hide(faces) {
      hidden = new Set();
      for (let f = 0; f < faces.length; f += 3) {
        hidden.add([faces[f], faces[f + 1], faces[f + 2]].sort((a, b) => a - b).join(','));
      }
      shownBody = drop(shownBody);
    },
    stamps: () => Object.fromEntries(Object.entries(stats.meshes).map(([key, m]) => [key, m.stamp ?? null])),
    capture,
  };
}
