// The surface as the viewer holds it: vertices and triangles by their stable ids, kept
// current from a snapshot, topology deltas and position frames — the same rules as the
// server's SurfaceReplica, including its hash, so tests can compare them exactly.

export class Surface {
  constructor() {
    this.clear();
  }

  clear() {
    this.version = -1;
    this.vertices = new Map(); // id -> { slot, x, y, z, material }
    this.triangles = new Map(); // id -> [a, b, c] vertex ids
    this.freeSlots = [];
    this.slotCount = 0;
    this.outerEdges = new Set(); // border edges of the snapshot (not wounds)
    this.topologyChanged = true;
    this.positionsChanged = true;
  }

  /** Replaces everything with a snapshot. */
  loadSnapshot(s) {
    this.clear();
    this.version = s.version;
    for (let k = 0; k < s.vertex_ids.length; k++) {
      this.addVertex(s.vertex_ids[k], s.positions_m[3 * k], s.positions_m[3 * k + 1], s.positions_m[3 * k + 2], s.materials[k]);
    }
    for (let k = 0; k < s.triangle_ids.length; k++) {
      this.triangles.set(s.triangle_ids[k], [s.triangle_vertices[3 * k], s.triangle_vertices[3 * k + 1], s.triangle_vertices[3 * k + 2]]);
    }
    for (const key of this.borderEdges()) this.outerEdges.add(key);
  }

  addVertex(id, x, y, z, material) {
    const slot = this.freeSlots.length ? this.freeSlots.pop() : this.slotCount++;
    this.vertices.set(id, { slot, x, y, z, material });
  }

  /** Applies a delta; false (and nothing changed) when it does not follow this version. */
  applyDelta(d) {
    if (d.version !== this.version + 1) return false;
    for (const id of d.removed_triangle_ids) this.triangles.delete(id);
    for (const id of d.removed_vertex_ids) {
      const v = this.vertices.get(id);
      if (v) {
        this.freeSlots.push(v.slot);
        this.vertices.delete(id);
      }
    }
    for (let k = 0; k < d.added_vertex_ids.length; k++) {
      this.addVertex(d.added_vertex_ids[k], d.added_positions_m[3 * k], d.added_positions_m[3 * k + 1], d.added_positions_m[3 * k + 2], d.added_materials[k]);
    }
    for (let k = 0; k < d.added_triangle_ids.length; k++) {
      this.triangles.set(d.added_triangle_ids[k], [d.added_triangle_vertices[3 * k], d.added_triangle_vertices[3 * k + 1], d.added_triangle_vertices[3 * k + 2]]);
    }
    this.version = d.version;
    this.topologyChanged = true;
    this.positionsChanged = true;
    return true;
  }

  /** Applies a Positions frame (ids are delta-encoded). */
  applyPositions(p) {
    let id = 0;
    for (let k = 0; k < p.id_deltas.length; k++) {
      id += p.id_deltas[k];
      const v = this.vertices.get(id);
      if (v) {
        v.x = p.positions_m[3 * k];
        v.y = p.positions_m[3 * k + 1];
        v.z = p.positions_m[3 * k + 2];
      }
    }
    this.positionsChanged = true;
  }

  /** Edges used by one triangle, as "a,b" keys with a < b. */
  borderEdges() {
    const count = new Map();
    for (const t of this.triangles.values()) {
      for (let k = 0; k < 3; k++) {
        const a = t[k];
        const b = t[(k + 1) % 3];
        const key = a < b ? `${a},${b}` : `${b},${a}`;
        count.set(key, (count.get(key) || 0) + 1);
      }
    }
    const out = [];
    for (const [key, n] of count) if (n === 1) out.push(key);
    return out;
  }

  /** Border edges that were not border in the first snapshot: the wounds' lips. */
  lipEdges() {
    return this.borderEdges().filter((key) => !this.outerEdges.has(key));
  }

  bounds() {
    const lo = [Infinity, Infinity, Infinity];
    const hi = [-Infinity, -Infinity, -Infinity];
    for (const v of this.vertices.values()) {
      const p = [v.x, v.y, v.z];
      for (let k = 0; k < 3; k++) {
        lo[k] = Math.min(lo[k], p[k]);
        hi[k] = Math.max(hi[k], p[k]);
      }
    }
    return { lo, hi };
  }

  /** FNV-1a 64 over exactly what the server's SurfaceSnapshot::surface_hash covers. */
  hash() {
    const h = new Fnv64();
    h.u64(this.version);
    const ids = [...this.vertices.keys()].sort((a, b) => a - b);
    const f32 = new Float32Array(1);
    const bits = new Uint32Array(f32.buffer);
    for (const id of ids) {
      const v = this.vertices.get(id);
      h.u32(id);
      for (const c of [v.x, v.y, v.z]) {
        f32[0] = c;
        h.u32(bits[0]);
      }
      h.u32(v.material);
    }
    h.byte(0xff);
    for (const id of [...this.triangles.keys()].sort((a, b) => a - b)) {
      h.u32(id);
      for (const v of this.triangles.get(id)) h.u32(v);
    }
    return h.hex();
  }
}

class Fnv64 {
  constructor() {
    this.value = 0xcbf29ce484222325n;
  }
  byte(b) {
    this.value ^= BigInt(b & 0xff);
    this.value = (this.value * 0x100000001b3n) & 0xffffffffffffffffn;
  }
  u32(v) {
    for (let k = 0; k < 4; k++) this.byte((v >>> (8 * k)) & 0xff);
  }
  u64(v) {
    const big = BigInt(v);
    for (let k = 0n; k < 8n; k++) this.byte(Number((big >> (8n * k)) & 0xffn));
  }
  hex() {
    return this.value.toString(16).padStart(16, '0');
  }
}
