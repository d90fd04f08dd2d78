// The morph of a person model in the browser: mirrors models/rig.py (Rig.morph of
// Rig.from_tangent) with the weights rebuilt from the rig file (models/webmodel.py, "Rig").
//
// At load, once: each vertex p_n is moved to the kernel space (models.rig.lips_apart: y
// lowered by lip_drop at lip_vertices), its row of the RBF system is evaluated,
//     rows(p) = [h_i(||p - x_i||)]_i ++ alpha [(p - x0) / ell, 1]
// (h_i(r) = sqrt(r^2 + s_i^2), the multiquadric, or exp(-(r / s_i)^2), the Gaussian, which
// has no affine part; models/morph.py), and B[n] = rows(p_n) @ Z9, Z9 (M + 4, 9) the file's
// ``z``; the eyeballs' rows (``frozen``) are zero. B is stored float32, as Rig.weights.
// Each frame: d_k = u_k t1_k + v_k t2_k for the 9 residuals (u, v), and
//     vertices = v + B @ d          (one (N, 9) @ (9, 3) product and one add).

export class Rig {
  // positions: Float32Array(N * 3), the neutral vertices, mm (the glb's POSITION).
  // rig: {header, arrays} of the rig file (model.js reads and checks it).
  constructor(positions, rig) {
    const { header, arrays } = rig;
    const n = positions.length / 3;
    const centres = arrays.centres, shape = arrays.shape, z = arrays.z;
    const m = shape.length;
    const affine = header.kernel === "multiquadric";
    const columns = m + (affine ? 4 : 0);
    const origin = arrays.origin, scale = header.scale, balance = header.balance;
    const drop = new Float64Array(n);
    arrays.lip_vertices.forEach((vertex, i) => { drop[vertex] = arrays.lip_drop[i]; });
    const weights = new Float32Array(n * 9);
    const row = new Float64Array(columns);
    for (let v = 0; v < n; v++) {
      const px = positions[3 * v], py = positions[3 * v + 1] - drop[v], pz = positions[3 * v + 2];
      for (let i = 0; i < m; i++) {
        const dx = px - centres[3 * i], dy = py - centres[3 * i + 1], dz = pz - centres[3 * i + 2];
        const r2 = dx * dx + dy * dy + dz * dz;
        row[i] = affine ? Math.sqrt(r2 + shape[i] * shape[i]) : Math.exp(-r2 / (shape[i] * shape[i]));
      }
      if (affine) {
        row[m] = balance * (px - origin[0]) / scale;
        row[m + 1] = balance * (py - origin[1]) / scale;
        row[m + 2] = balance * (pz - origin[2]) / scale;
        row[m + 3] = balance;
      }
      for (let k = 0; k < 9; k++) {
        let sum = 0;
        for (let i = 0; i < columns; i++) sum += row[i] * z[9 * i + k];
        weights[9 * v + k] = sum;
      }
    }
    for (const vertex of arrays.frozen) weights.fill(0, 9 * vertex, 9 * vertex + 9);
    this.weights = weights;  // (N, 9) row-major, Rig.weights
    this.tangents = arrays.tangents;  // (9, 2, 3), Rig.tangents
    this.neutral = positions;
    this.count = n;
    this._out = new Float32Array(n * 3);
    this._d = new Float32Array(27);
  }

  // residuals: (9, 2) row-major tangent-frame residuals (u, v), mm (a FrameState's).
  // -> (9, 3) row-major model-space displacements (Rig.from_tangent), float32.
  fromTangent(residuals) {
    const d = this._d, t = this.tangents;
    for (let k = 0; k < 9; k++) {
      const u = residuals[2 * k], v = residuals[2 * k + 1];
      for (let j = 0; j < 3; j++) d[3 * k + j] = u * t[6 * k + j] + v * t[6 * k + 3 + j];
    }
    return d;
  }

  // residuals: (9, 2) tangent residuals -> Float32Array(N * 3), the frame's vertices, mm
  // (a buffer the next call overwrites).
  morph(residuals) {
    const d = this.fromTangent(residuals), w = this.weights, v = this.neutral, out = this._out;
    for (let n = 0; n < this.count; n++) {
      let x = 0, y = 0, z = 0;
      const b = 9 * n;
      for (let k = 0; k < 9; k++) {
        const weight = w[b + k];
        x += weight * d[3 * k];
        y += weight * d[3 * k + 1];
        z += weight * d[3 * k + 2];
      }
      out[3 * n] = v[3 * n] + x;
      out[3 * n + 1] = v[3 * n + 1] + y;
      out[3 * n + 2] = v[3 * n + 2] + z;
    }
    return out;
  }
}
