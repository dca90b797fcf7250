//! Delaunay triangulation of integer points: Bowyer-Watson insertion in Morton order with a
//! visibility walk, exact `i128` orientation and in-circle predicates (support points lie on a
//! grid, so co-circular quadruples are the rule, not the exception, and floating-point tests
//! would flip on them).
//!
//! The enclosing triangle is finite (2^22 px from the centre), so a hull triangle whose
//! circumcircle reaches that far (three hull points within about 2e-4 rad of a straight line)
//! can be missing; ELAS fills such slivers by gap interpolation.

const NONE: u32 = u32::MAX;
const FAR: i64 = 1 << 22;

#[derive(Clone, Copy)]
struct Tri {
    /// Vertices, counter-clockwise.
    v: [u32; 3],
    /// Neighbour across the edge opposite `v[i]`.
    n: [u32; 3],
}

type P = (i64, i64);

fn orient(a: P, b: P, c: P) -> i128 {
    (b.0 - a.0) as i128 * (c.1 - a.1) as i128 - (b.1 - a.1) as i128 * (c.0 - a.0) as i128
}

/// > 0 when `d` lies strictly inside the circle through the counter-clockwise `a`, `b`, `c`.
fn in_circle(a: P, b: P, c: P, d: P) -> i128 {
    let r = |p: P| {
        let (x, y) = ((p.0 - d.0) as i128, (p.1 - d.1) as i128);
        (x, y, x * x + y * y)
    };
    let (ax, ay, a2) = r(a);
    let (bx, by, b2) = r(b);
    let (cx, cy, c2) = r(c);
    ax * (by * c2 - b2 * cy) - ay * (bx * c2 - b2 * cx) + a2 * (bx * cy - by * cx)
}

fn morton(x: u32, y: u32) -> u64 {
    let spread = |v: u32| {
        let mut v = v as u64 & 0xffff_ffff;
        v = (v | (v << 16)) & 0x0000_ffff_0000_ffff;
        v = (v | (v << 8)) & 0x00ff_00ff_00ff_00ff;
        v = (v | (v << 4)) & 0x0f0f_0f0f_0f0f_0f0f;
        v = (v | (v << 2)) & 0x3333_3333_3333_3333;
        (v | (v << 1)) & 0x5555_5555_5555_5555
    };
    spread(x) | (spread(y) << 1)
}

/// Triangles (indices into `pts`, counter-clockwise) of the Delaunay triangulation. Duplicate
/// points are triangulated once (the first index); collinear input gives no triangle.
/// Coordinates must lie within +-2^20.
pub fn triangulate(pts: &[(i32, i32)]) -> Vec<[u32; 3]> {
    if pts.len() < 3 {
        return Vec::new();
    }
    let (mut x0, mut y0, mut x1, mut y1) = (i32::MAX, i32::MAX, i32::MIN, i32::MIN);
    for &(x, y) in pts {
        x0 = x0.min(x);
        y0 = y0.min(y);
        x1 = x1.max(x);
        y1 = y1.max(y);
    }
    // Insertion order: Morton, duplicates dropped.
    let mut order: Vec<u32> = (0..pts.len() as u32).collect();
    let key = |i: u32| {
        let (x, y) = pts[i as usize];
        (morton((x - x0) as u32, (y - y0) as u32), i)
    };
    order.sort_unstable_by_key(|&i| key(i));
    order.dedup_by(|b, a| pts[*a as usize] == pts[*b as usize]);
    let n = pts.len();
    let (cx, cy) = ((x0 as i64 + x1 as i64) / 2, (y0 as i64 + y1 as i64) / 2);
    let mut p: Vec<P> = pts.iter().map(|&(x, y)| (x as i64, y as i64)).collect();
    p.push((cx - FAR, cy - FAR));
    p.push((cx + FAR, cy - FAR));
    p.push((cx, cy + FAR));
    let s = n as u32;
    let mut tris = vec![Tri {
        v: [s, s + 1, s + 2],
        n: [NONE; 3],
    }];
    let mut alive = vec![true];
    let mut mark: Vec<u32> = vec![0];
    let mut stamp = 0u32;
    let mut last = 0usize;
    let mut stack = Vec::new();
    let mut cavity = Vec::new();
    let mut boundary: Vec<(u32, u32, u32)> = Vec::new();
    let mut fresh: Vec<usize> = Vec::new();
    for &pi in &order {
        let q = p[pi as usize];
        // Locate: walk towards q; fall back to a scan if the walk does not end.
        let mut t = last;
        let mut steps = 0;
        'walk: loop {
            let tr = tris[t];
            for i in 0..3 {
                let (a, b) = (tr.v[(i + 1) % 3], tr.v[(i + 2) % 3]);
                if orient(p[a as usize], p[b as usize], q) < 0 {
                    t = tr.n[i] as usize;
                    steps += 1;
                    if steps > tris.len() {
                        t = (0..tris.len())
                            .find(|&k| {
                                alive[k]
                                    && (0..3).all(|i| {
                                        let v = tris[k].v;
                                        orient(
                                            p[v[(i + 1) % 3] as usize],
                                            p[v[(i + 2) % 3] as usize],
                                            q,
                                        ) >= 0
                                    })
                            })
                            .unwrap_or(last);
                        break 'walk;
                    }
                    continue 'walk;
                }
            }
            break;
        }
        if tris[t].v.iter().any(|&v| p[v as usize] == q) {
            continue;
        }
        // Cavity: every triangle whose circumcircle holds q, grown from the one containing it.
        stamp += 2;
        let (inside, outside) = (stamp, stamp + 1);
        cavity.clear();
        boundary.clear();
        stack.clear();
        stack.push(t);
        mark[t] = inside;
        while let Some(c) = stack.pop() {
            cavity.push(c);
            let tr = tris[c];
            for i in 0..3 {
                let nb = tr.n[i];
                let crosses = nb != NONE && {
                    let nbu = nb as usize;
                    if mark[nbu] == inside {
                        continue;
                    }
                    if mark[nbu] == outside {
                        false
                    } else {
                        let v = tris[nbu].v;
                        let hit =
                            in_circle(p[v[0] as usize], p[v[1] as usize], p[v[2] as usize], q) > 0;
                        mark[nbu] = if hit { inside } else { outside };
                        if hit {
                            stack.push(nbu);
                        }
                        hit
                    }
                };
                if !crosses {
                    boundary.push((tr.v[(i + 1) % 3], tr.v[(i + 2) % 3], nb));
                }
            }
        }
        for &c in &cavity {
            alive[c] = false;
        }
        // Fan the cavity's boundary to q.
        fresh.clear();
        for &(a, b, out) in &boundary {
            let id = tris.len();
            tris.push(Tri {
                v: [a, b, pi],
                n: [NONE, NONE, out],
            });
            alive.push(true);
            mark.push(0);
            if out != NONE {
                let o = &mut tris[out as usize];
                for k in 0..3 {
                    let (oa, ob) = (o.v[(k + 1) % 3], o.v[(k + 2) % 3]);
                    if oa == b && ob == a {
                        o.n[k] = id as u32;
                    }
                }
            }
            fresh.push(id);
        }
        // Neighbours among the new triangles: (a, b, q) meets (b, c, q) across b-q, opposite a.
        for &x in &fresh {
            let [a, b, _] = tris[x].v;
            for &y in &fresh {
                let [ya, yb, _] = tris[y].v;
                if ya == b {
                    tris[x].n[0] = y as u32;
                }
                if yb == a {
                    tris[x].n[1] = y as u32;
                }
            }
        }
        last = fresh[0];
    }
    tris.iter()
        .zip(&alive)
        .filter(|(t, &a)| a && t.v.iter().all(|&v| (v as usize) < n))
        .map(|(t, _)| t.v)
        .collect()
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn area2(pts: &[(i32, i32)], t: [u32; 3]) -> i128 {
        let q = |i: u32| (pts[i as usize].0 as i64, pts[i as usize].1 as i64);
        orient(q(t[0]), q(t[1]), q(t[2]))
    }

    fn hull_area2(pts: &[(i32, i32)]) -> i128 {
        let mut s: Vec<P> = pts.iter().map(|&(x, y)| (x as i64, y as i64)).collect();
        s.sort();
        s.dedup();
        let mut h: Vec<P> = Vec::new();
        for pass in 0..2 {
            let start = h.len();
            let it: Box<dyn Iterator<Item = &P>> = if pass == 0 {
                Box::new(s.iter())
            } else {
                Box::new(s.iter().rev())
            };
            for &q in it {
                while h.len() >= start + 2 && orient(h[h.len() - 2], h[h.len() - 1], q) <= 0 {
                    h.pop();
                }
                h.push(q);
            }
            h.pop();
        }
        (0..h.len())
            .map(|i| {
                let (a, b) = (h[i], h[(i + 1) % h.len()]);
                a.0 as i128 * b.1 as i128 - b.0 as i128 * a.1 as i128
            })
            .sum()
    }

    fn check(pts: &[(i32, i32)]) {
        let tris = triangulate(pts);
        let q = |i: u32| (pts[i as usize].0 as i64, pts[i as usize].1 as i64);
        for &t in &tris {
            assert!(area2(pts, t) > 0, "triangle {t:?} not counter-clockwise");
            for (k, &pt) in pts.iter().enumerate() {
                let d = (pt.0 as i64, pt.1 as i64);
                assert!(
                    in_circle(q(t[0]), q(t[1]), q(t[2]), d) <= 0,
                    "point {k} inside the circumcircle of {t:?}"
                );
            }
        }
        let total: i128 = tris.iter().map(|&t| area2(pts, t)).sum();
        assert_eq!(total, hull_area2(pts), "triangles do not tile the hull");
    }

    #[test]
    fn random_points_give_a_delaunay_tiling_of_the_hull() {
        let mut s = 7u64;
        let mut next = |m: i32| {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 33) % m as u64) as i32
        };
        let pts: Vec<(i32, i32)> = (0..400).map(|_| (next(640), next(480))).collect();
        check(&pts);
    }

    #[test]
    fn a_full_grid_with_cocircular_points_and_duplicates() {
        let mut pts: Vec<(i32, i32)> = (0..12)
            .flat_map(|v| (0..15).map(move |u| (u * 5, v * 5)))
            .collect();
        pts.push((10, 10));
        pts.push((0, 0));
        check(&pts);
        // 11 x 14 squares, two triangles each.
        assert_eq!(triangulate(&pts).len(), 2 * 11 * 14);
    }

    #[test]
    fn degenerate_inputs_give_no_triangles() {
        assert!(triangulate(&[(0, 0), (1, 1)]).is_empty());
        assert!(triangulate(&[(0, 0), (1, 1), (2, 2), (5, 5)]).is_empty());
        assert_eq!(triangulate(&[(0, 0), (4, 0), (0, 3)]).len(), 1);
    }
}
