// Attitude conversions for the form: any of the request's three forms to a unit quaternion
// [w, x, y, z] (scalar first, of the active rotation R), as README "Conventions" defines them.

/** The Gibbs vector q of the paper's Cayley transform: q = −[x, y, z] / w. */
function fromGibbs(q) {
  const n = Math.hypot(1, ...q);
  return [1 / n, -q[0] / n, -q[1] / n, -q[2] / n];
}

/** Rotation matrix (rows) to quaternion, by the largest of 1 + tr R and 1 + 2R_ii − tr R. */
function fromMatrix(R) {
  const tr = R[0][0] + R[1][1] + R[2][2];
  let q;
  if (tr > 0) {
    const s = 2 * Math.sqrt(1 + tr);
    q = [s / 4, (R[2][1] - R[1][2]) / s, (R[0][2] - R[2][0]) / s, (R[1][0] - R[0][1]) / s];
  } else if (R[0][0] > R[1][1] && R[0][0] > R[2][2]) {
    const s = 2 * Math.sqrt(1 + R[0][0] - R[1][1] - R[2][2]);
    q = [(R[2][1] - R[1][2]) / s, s / 4, (R[0][1] + R[1][0]) / s, (R[0][2] + R[2][0]) / s];
  } else if (R[1][1] > R[2][2]) {
    const s = 2 * Math.sqrt(1 + R[1][1] - R[0][0] - R[2][2]);
    q = [(R[0][2] - R[2][0]) / s, (R[0][1] + R[1][0]) / s, s / 4, (R[1][2] + R[2][1]) / s];
  } else {
    const s = 2 * Math.sqrt(1 + R[2][2] - R[0][0] - R[1][1]);
    q = [(R[1][0] - R[0][1]) / s, (R[0][2] + R[2][0]) / s, (R[1][2] + R[2][1]) / s, s / 4];
  }
  const sign = q[0] < 0 ? -1 : 1;
  return q.map((c) => Number((sign * c).toPrecision(10)));
}

/** The pose's attitude as a quaternion, or null when it has no readable one. */
export function quaternionOf(pose) {
  const isVector = (v, n) => Array.isArray(v) && v.length === n && v.every(Number.isFinite);
  if (isVector(pose.quaternion, 4)) return pose.quaternion;
  if (isVector(pose.q, 3)) return fromGibbs(pose.q);
  if (Array.isArray(pose.R) && pose.R.length === 3 && pose.R.every((r) => isVector(r, 3))) {
    return fromMatrix(pose.R);
  }
  return null;
}
