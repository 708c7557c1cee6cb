// Wire format of the binary WebSocket messages (agentdress_ros/display/scene.py writes them):
//   uint32 little-endian header length H, H bytes of JSON (space-padded to a multiple of 4), then the payload.
//   header {type: "mesh", key, agent, garment, color, faces: F, vertices: V}: payload F*3 uint32 + V*3 float32
//     with skin: K, bones: B (a skinned mesh) then V*K uint16 bone indices (zero-padded to 4 bytes), V*K float32
//     weights
//   header {type: "frame", seq, meshes: [{key, vertices: V | bones: B, offset, stamp}]}: payload of float32
//   vertices (V*3) or a skinned mesh's bone transforms (B*12, rows of 3x4), each mesh's block at its byte offset
//   (4-byte aligned, so it is read in place as a Float32Array)
const decoder = new TextDecoder();

export function decodeMessage(buffer) {
  const length = new DataView(buffer).getUint32(0, true);
  const header = JSON.parse(decoder.decode(new Uint8Array(buffer, 4, length)));
  return { header, payloadOffset: 4 + length };
}
