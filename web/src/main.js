// The immersive display client: every agent and garment the node(s) publish, drawn with three.js, in WebXR on a
// headset. Frames arrive over a WebSocket (see frames.js for the wire format); the page's own URL carries the
// access token as its first path segment, so every relative URL (modules, the socket) carries it too.
import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { VRButton } from 'three/addons/webxr/VRButton.js';
import { Panel } from './panel.js';

const stats = {
  renderer: null, three: THREE.REVISION, connected: false, renderFrames: 0, xrFrames: 0, framesReceived: 0,
  unposedFrames: 0, // frames drawn with a skinned mesh that has no pose yet (its rest pose: a body under posed cloth)
  fps: {}, meshes: {}, startedAt: performance.now(),
};
window.agentdress = stats; // read by the tests and handy in the console
// a mesh's current vertices (V * 3 numbers, the node's Z-up metres) and the nodes' status, for tests and scripts
// (a skinned mesh's as the page skins them: three.js' CPU twin of its skinning shader)
stats.positions = (key) => {
  const mesh = meshes.get(key)?.mesh;
  if (!mesh) return [];
  if (!mesh.isSkinnedMesh) return Array.from(mesh.geometry.attributes.position.array);
  const out = [];
  const v = new THREE.Vector3();
  for (let i = 0; i < mesh.geometry.attributes.position.count; i++) out.push(...mesh.getVertexPosition(i, v).toArray());
  return out;
};
stats.status = () => Object.fromEntries(panel.status);

// A software rasteriser (SwiftShader, llvmpipe: no GPU) draws without multisampling at one pixel per CSS pixel.
const software = (() => {
  const gl = document.createElement('canvas').getContext('webgl2') || document.createElement('canvas').getContext('webgl');
  const debug = gl && gl.getExtension('WEBGL_debug_renderer_info');
  const name = gl ? String(gl.getParameter(debug ? debug.UNMASKED_RENDERER_WEBGL : gl.RENDERER)) : '';
  gl?.getExtension('WEBGL_lose_context')?.loseContext();
  return /swiftshader|llvmpipe|software/i.test(name);
})();
const renderer = new THREE.WebGLRenderer({ antialias: !software });
renderer.setPixelRatio(software ? 1 : window.devicePixelRatio);
renderer.setSize(window.innerWidth, window.innerHeight);
renderer.xr.enabled = true;
renderer.xr.setReferenceSpaceType('local-floor');
document.body.appendChild(renderer.domElement);
stats.renderer = renderer.isWebGLRenderer ? 'WebGLRenderer' : String(renderer.constructor.name);
stats.software = software;
stats.webgl = renderer.capabilities.isWebGL2 ? 'webgl2' : 'webgl';
const vrButton = VRButton.createButton(renderer);
vrButton.id = 'vr-button';
document.body.appendChild(vrButton);

const scene = new THREE.Scene();
scene.background = new THREE.Color(0x20242a);
scene.add(new THREE.HemisphereLight(0xf2f4ff, 0x3a3530, 1.6));
const sun = new THREE.DirectionalLight(0xffffff, 1.8);
sun.position.set(2, 4, 3);
scene.add(sun);
const floor = new THREE.Mesh(new THREE.CircleGeometry(12, 64),
  new THREE.MeshStandardMaterial({ color: 0x3b4048, roughness: 0.95 }));
floor.rotation.x = -Math.PI / 2;
scene.add(floor);
const grid = new THREE.GridHelper(24, 48, 0x59606b, 0x4a5059);
grid.position.y = 0.001;
scene.add(grid);

// The node's world is Z up (ROS REP-103); three.js is Y up: one rotation for everything received.
const world = new THREE.Group();
world.rotation.x = -Math.PI / 2;
scene.add(world);

const camera = new THREE.PerspectiveCamera(45, window.innerWidth / window.innerHeight, 0.05, 200);
camera.position.set(0, 1.3, 3.6);
const controls = new OrbitControls(camera, renderer.domElement);
controls.target.set(0, 0.95, 0);
controls.update();
let framed = false;

renderer.xr.addEventListener('sessionstart', () => { world.position.set(0, 0, -1.6); });
renderer.xr.addEventListener('sessionend', () => { world.position.set(0, 0, 0); });

const meshes = new Map(); // key "agent/garment" -> {mesh, agent, garment, dirty}
const panel = new Panel((agent, values) => send({ type: 'shape', agent, values }));
stats.world = world; // the three.js objects of the meshes (tests)

// A skinned mesh (the body): its rest, bone indices and weights once; each frame only its bone transforms, which
// the GPU applies (linear blend skinning, as the node does). Each bone's matrixWorld is the frame's rest-to-posed
// transform; the bones sit outside the scene graph, so three.js never recomputes them, and the detached bind
// (identity) keeps the skinned vertices in the mesh's own (the node's) frame.
function skinnedMesh(geometry, material, header, indices, weights) {
  geometry.setAttribute('skinIndex', new THREE.Uint16BufferAttribute(new Uint16Array(indices), header.skin));
  geometry.setAttribute('skinWeight', new THREE.Float32BufferAttribute(new Float32Array(weights), header.skin));
  const bones = Array.from({ length: header.bones }, () => {
    const bone = new THREE.Bone();
    bone.matrixAutoUpdate = false;
    return bone;
  });
  const mesh = new THREE.SkinnedMesh(geometry, material);
  mesh.bindMode = THREE.DetachedBindMode;
  mesh.bind(new THREE.Skeleton(bones), new THREE.Matrix4());
  return mesh;
}

function setBones(mesh, buffer) {
  const t = new Float32Array(buffer); // B x 12: rows of 3x4 transforms
  const bones = mesh.skeleton.bones;
  for (let b = 0; b < bones.length && 12 * b + 11 < t.length; b++) {
    const o = 12 * b;
    bones[b].matrixWorld.set(t[o], t[o + 1], t[o + 2], t[o + 3], t[o + 4], t[o + 5], t[o + 6], t[o + 7],
      t[o + 8], t[o + 9], t[o + 10], t[o + 11], 0, 0, 0, 1);
  }
}

function setMesh(header, faces, vertices, indices, weights) {
  const old = meshes.get(header.key);
  // a skinned mesh bound again (a new body shape) keeps its pose until its next bones: never a frame in rest pose
  const pose = old && old.mesh.isSkinnedMesh && header.skin ? old.mesh.skeleton.bones.map((b) => b.matrixWorld.clone())
    : null;
  const stamp = pose ? stats.meshes[header.key]?.stamp : undefined;
  if (old) disposeMesh(old.mesh);
  const geometry = new THREE.BufferGeometry();
  const position = new THREE.BufferAttribute(new Float32Array(vertices), 3);
  if (!header.skin) position.setUsage(THREE.DynamicDrawUsage);
  geometry.setAttribute('position', position);
  geometry.setIndex(new THREE.BufferAttribute(new Uint32Array(faces), 1));
  geometry.computeVertexNormals(); // a skinned mesh's rest normals: the GPU skins them with the vertices
  const color = new THREE.Color().setRGB(...header.color, THREE.SRGBColorSpace);
  const material = new THREE.MeshLambertMaterial({ // matte cloth and skin, smooth-shaded by vertex normals
    color,
    side: header.garment === 'body' ? THREE.FrontSide : THREE.DoubleSide, // open garments show their inside
    // the body a hair behind the cloth in depth: where skin and cloth meet at a hem the cloth wins
    polygonOffset: header.garment === 'body', polygonOffsetFactor: 1, polygonOffsetUnits: 1,
  });
  const mesh = header.skin ? skinnedMesh(geometry, material, header, indices, weights)
    : new THREE.Mesh(geometry, material);
  mesh.frustumCulled = false; // vertices move every frame: no stale bounding sphere
  mesh.name = header.key;
  world.add(mesh);
  meshes.set(header.key, { mesh, agent: header.agent, garment: header.garment, dirty: false,
    posed: !header.skin || Boolean(pose) });
  stats.meshes[header.key] = { vertices: header.vertices, faces: header.faces, frames: 0, color: header.color,
    skinned: Boolean(header.skin), stamp };
  if (pose && pose.length === mesh.skeleton.bones.length) {
    mesh.skeleton.bones.forEach((bone, b) => bone.matrixWorld.copy(pose[b]));
  }
  panel.addMesh(header);
}

function setFrames(frames) {
  stats.framesReceived += 1;
  for (const m of frames) {
    const entry = meshes.get(m.key);
    if (!entry) continue;
    if (m.bones) {
      if (!entry.mesh.isSkinnedMesh) continue;
      setBones(entry.mesh, m.bones);
      entry.posed = true;
      stats.meshes[m.key].frames += 1;
      stats.meshes[m.key].stamp = m.stamp;
      continue;
    }
    if (entry.mesh.isSkinnedMesh) continue; // vertices of a mesh now skinned: its bones are on the way
    const position = entry.mesh.geometry.attributes.position;
    if (position.count * 12 !== m.vertices.byteLength) continue; // topology changed; its new mesh is on the way
    position.array.set(new Float32Array(m.vertices));
    position.needsUpdate = true;
    entry.dirty = true;
    stats.meshes[m.key].frames += 1;
    stats.meshes[m.key].stamp = m.stamp;
  }
}

const worker = new Worker(new URL('./socket-worker.js', import.meta.url), { type: 'module' });
function send(message) { worker.postMessage({ kind: 'send', message }); }

worker.onmessage = (event) => {
  const data = event.data;
  if (data.kind === 'frames') setFrames(data.meshes);
  else if (data.kind === 'mesh') setMesh(data.header, data.faces, data.vertices, data.indices, data.weights);
  else if (data.kind === 'fps') panel.setMeshFps(data.fps);
  else if (data.kind === 'open') { stats.connected = true; panel.setConnection('live'); }
  else if (data.kind === 'closed') { stats.connected = false; panel.setConnection('reconnecting'); }
  else if (data.kind === 'text') {
    const message = data.message;
    if (message.type === 'hello') panel.setPhenotypes(message.phenotypes);
    else if (message.type === 'status') panel.setStatus(message.source, message.status);
    else if (message.type === 'remove') removeMesh(message.key);
    else if (message.type === 'error' || message.type === 'warning') console.warn('agentdress server:', message.message);
  }
};

function connect() {
  const url = new URL('ws', window.location.href);
  url.protocol = url.protocol === 'https:' ? 'wss:' : 'ws:';
  worker.postMessage({ kind: 'connect', url: url.href });
  worker.postMessage({ kind: 'want' });
}

// Frees what a mesh holds on the GPU: its geometry's buffers, its material's program use, a skinned mesh's bone
// texture.
function disposeMesh(mesh) {
  world.remove(mesh);
  mesh.geometry.dispose();
  mesh.material.dispose();
  if (mesh.isSkinnedMesh) mesh.skeleton.dispose();
}

function removeMesh(key) {
  const entry = meshes.get(key);
  if (!entry) return;
  disposeMesh(entry.mesh);
  meshes.delete(key);
  delete stats.meshes[key];
  panel.removeMesh(key);
}

function frameCamera() {
  const box = new THREE.Box3();
  for (const { mesh } of meshes.values()) box.expandByObject(mesh);
  if (box.isEmpty()) return;
  const centre = box.getCenter(new THREE.Vector3());
  const size = box.getSize(new THREE.Vector3());
  const distance = Math.max(size.y * 1.6, Math.max(size.x, size.z) * 1.2, 2.5);
  controls.target.copy(centre);
  camera.position.set(centre.x + 0.25 * distance, centre.y + 0.15 * distance, centre.z + distance);
  controls.update();
  framed = true;
}

// Without a GPU a frame takes tens of milliseconds to draw: at most 20 a second, so the page stays responsive.
const minFrameMs = software ? 50 : 0;
let lastRender = -Infinity;

function render() {
  const now = performance.now();
  if (!renderer.xr.isPresenting && now - lastRender < minFrameMs) return;
  lastRender = now;
  for (const entry of meshes.values()) {
    if (!entry.posed) stats.unposedFrames += 1;
    if (entry.dirty) {
      entry.mesh.geometry.computeVertexNormals(); // smooth shading from this frame's vertices
      entry.dirty = false;
    }
  }
  if (!framed && meshes.size && stats.framesReceived > 0) frameCamera();
  stats.renderFrames += 1;
  if (renderer.xr.isPresenting) stats.xrFrames += 1;
  stats.fps = panel.update(now);
  stats.meshFps = panel.meshFps;
  renderer.render(scene, camera);
  worker.postMessage({ kind: 'want' }); // the newest vertices for the next frame
}

window.addEventListener('resize', () => {
  camera.aspect = window.innerWidth / window.innerHeight;
  camera.updateProjectionMatrix();
  renderer.setSize(window.innerWidth, window.innerHeight);
});

renderer.setAnimationLoop(render);
connect();
// ?look=1: the viewer's-eye check (web/src/look.js, `agentdress bench look`) draws this page's meshes off screen
if (new URLSearchParams(window.location.search).has('look')) {
  import('./look.js').then((look) => look.install({ THREE, renderer, scene, world, meshes, stats }));
}
