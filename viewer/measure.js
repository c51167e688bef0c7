// The viewer's distance / height measure: two picked points in world metres and the local vertical there.
// Returns the straight distance, the height difference along the local up (+ when b is above a) and the
// horizontal distance, all in metres.
export function measureBetween(a, b, up) {
  const d = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
  const n = Math.hypot(up[0], up[1], up[2]) || 1;
  const distance = Math.hypot(d[0], d[1], d[2]);
  const height = (d[0] * up[0] + d[1] * up[1] + d[2] * up[2]) / n;
  const horizontal = Math.sqrt(Math.max(0, distance * distance - height * height));
  return { distance, height, horizontal };
}

export function describeMeasure(m) {
  return `distance   ${m.distance.toFixed(3)} m\nheight     ${m.height >= 0 ? '+' : ''}${m.height.toFixed(3)} m` +
    `\nhorizontal ${m.horizontal.toFixed(3)} m`;
}
