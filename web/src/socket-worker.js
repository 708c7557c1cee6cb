// The WebSocket lives in a worker: frames are received, decoded and counted here even while the page's main thread
// is busy drawing. The page pulls: after each drawn frame it asks for the newest vertices of every mesh that changed
// (older frames in between are counted, not handed over), so a slow page never falls behind. Messages to the page:
//   {kind: 'open' | 'closed'}, {kind: 'text', message}, {kind: 'mesh', header, faces, vertices[, indices, weights]},
//   {kind: 'frames', meshes: [{key, stamp, vertices | bones: ArrayBuffer}]},
//   {kind: 'fps', fps: {mesh key: frames per second}}
// and from the page: {kind: 'connect', url}, {kind: 'want'} (ready for frames), {kind: 'send', message}.
import { decodeMessage } from './frames.js';

const WINDOW_MS = 2000;
const arrivals = new Map(); // mesh key -> arrival times (ms) within the window
let socket = null;
const latest = new Map(); // mesh key -> the newest frame not yet handed over: {key, vertices | bones}
let wanted = false;

function handOver() {
  if (!wanted || latest.size === 0) return;
  const meshes = [...latest.values()];
  latest.clear();
  wanted = false;
  postMessage({ kind: 'frames', meshes }, meshes.map((m) => m.vertices || m.bones));
}

function connect(url) {
  socket = new WebSocket(url);
  socket.binaryType = 'arraybuffer';
  socket.onopen = () => postMessage({ kind: 'open' });
  socket.onclose = () => {
    postMessage({ kind: 'closed' });
    setTimeout(() => connect(url), 1000);
  };
  socket.onmessage = (event) => {
    if (typeof event.data === 'string') {
      postMessage({ kind: 'text', message: JSON.parse(event.data) });
      return;
    }
    const { header, payloadOffset } = decodeMessage(event.data);
    if (header.type === 'mesh') {
      const facesEnd = payloadOffset + header.faces * 12;
      const faces = event.data.slice(payloadOffset, facesEnd);
      const verticesEnd = facesEnd + header.vertices * 12;
      const vertices = event.data.slice(facesEnd, verticesEnd);
      latest.delete(header.key); // frames of the old topology are void
      if (header.skin) { // a skinned mesh: its rest, then uint16 bone indices (padded to 4 bytes), float32 weights
        const count = header.vertices * header.skin;
        const indicesEnd = verticesEnd + count * 2;
        const indices = event.data.slice(verticesEnd, indicesEnd);
        const weightsStart = indicesEnd + ((4 - (indicesEnd % 4)) % 4);
        const weights = event.data.slice(weightsStart, weightsStart + count * 4);
        postMessage({ kind: 'mesh', header, faces, vertices, indices, weights }, [faces, vertices, indices, weights]);
      } else {
        postMessage({ kind: 'mesh', header, faces, vertices }, [faces, vertices]);
      }
    } else if (header.type === 'frame') {
      const now = performance.now();
      for (const m of header.meshes) {
        if (!arrivals.has(m.key)) arrivals.set(m.key, []);
        arrivals.get(m.key).push(now);
        const start = payloadOffset + m.offset;
        latest.set(m.key, m.bones !== undefined
          ? { key: m.key, stamp: m.stamp, bones: event.data.slice(start, start + m.bones * 48) }
          : { key: m.key, stamp: m.stamp, vertices: event.data.slice(start, start + m.vertices * 12) });
      }
      handOver();
    }
  };
}

setInterval(() => {
  const now = performance.now();
  const fps = {};
  for (const [key, times] of arrivals) {
    while (times.length && times[0] < now - WINDOW_MS) times.shift();
    fps[key] = times.length / (WINDOW_MS / 1000);
  }
  postMessage({ kind: 'fps', fps });
}, 250);

onmessage = (event) => {
  if (event.data.kind === 'connect') connect(event.data.url);
  else if (event.data.kind === 'want') { wanted = true; handOver(); }
  else if (event.data.kind === 'send' && socket && socket.readyState === WebSocket.OPEN) {
    socket.send(JSON.stringify(event.data.message));
  }
};
