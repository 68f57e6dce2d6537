//! `--compare DRIVER`: the same rays traced on Arbor and on another driver, compared hit by hit.
//! Owns the per-ray record the trace shader writes (`Hit`), the comparison rules and tolerances,
//! and the text and JSON of the result; it runs nothing on a device.
use std::fmt::Write as _;

use crate::report::json_str;

/// Relative tolerance on t, relative to the size of the numbers the hit is computed from:
/// |Δt| ≤ T_REL_TOL · (t + ‖origin‖∞ / ‖dir‖). Both sides compute the hit in f32 (lavapipe's edge
/// functions in f64) from vertices taken relative to the ray's origin, so rounding is a few ulps
/// (f32 epsilon 1.2e-7) of the coordinates, not of t: a short hit far from the world's origin
/// differs by more than a few ulps of its own t. Grazing hits amplify the rounding; 1e-5 (~80 ulps)
/// covers that and stays far below the distance between neighbouring surfaces of a mesh.
pub const T_REL_TOL: f32 = 1e-5;

/// Absolute tolerance on each barycentric coordinate (they lie in [0, 1]). They are edge
/// functions divided by the determinant, which is tiny for the slivers of scanned meshes, so f32
/// rounding moves them far more than t: on the full dragon, exact rational arithmetic puts both
/// Arbor's and lavapipe's barycentrics up to 7e-3 from the true value on a few dozen of a million
/// rays, and the two drivers differ by up to 9.5e-3. 2e-2 accepts that and still catches real
/// errors (swapped or misordered coordinates, another vertex order), which are of the order of the
/// coordinates themselves.
pub const BARY_ABS_TOL: f32 = 2e-2;

/// How close to an edge (smallest barycentric coordinate, u, v or 1 - u - v) a hit must lie for
/// a disagreement about it to be an edge case. Near an open edge (a mesh boundary, a soup
/// triangle) a ray rounded differently on its way into object space (each driver inverts the
/// instance transform its own way) legitimately hits or passes by: on 1,000 instances the two
/// drivers disagree this way with the hit 8e-5 and 2e-4 from the edge. A missed hit 1e-3 inside a
/// triangle is no rounding: it stays a mismatch.
pub const EDGE_TOL: f32 = 1e-3;

/// One ray as the shader reads it: origin, tmin, direction, tmax (32 bytes).
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct TraceRay {
    pub origin: [f32; 3],
    pub tmin: f32,
    pub dir: [f32; 3],
    pub tmax: f32,
}

impl TraceRay {

    pub fn to_bytes(self) -> [u8; 32] {
        let w = [self.origin[0], self.origin[1], self.origin[2], self.tmin, self.dir[0], self.dir[1], self.dir[2], self.tmax];
        let mut out = [0u8; 32];
        for (k, v) in w.iter().enumerate() {
            out[4 * k..4 * k + 4].copy_from_slice(&v.to_le_bytes());
        }
        out
    }
}

/// The committed intersection of one ray, as the shader writes it (32 bytes; kind 0 = miss,
/// and then every other field is 0).
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct Hit {
    pub t: f32,
    pub prim: u32,
    /// rayQueryGetIntersectionInstanceIdEXT: the instance's index in the TLAS.
    pub inst: u32,
    pub geom: u32,
    pub bary: [f32; 2],
    /// 0 none, 1 triangle, 2 generated.
    pub kind: u32,
    /// rayQueryGetIntersectionInstanceCustomIndexEXT.
    pub custom: u32,
}

impl Hit {
    pub const SIZE: usize = 32;

    /// `bytes` holds at least 32 bytes.
    pub fn from_bytes(b: &[u8]) -> Hit {
        let u = |k: usize| u32::from_le_bytes([b[4 * k], b[4 * k + 1], b[4 * k + 2], b[4 * k + 3]]);
        let f = |k: usize| f32::from_bits(u(k));
        Hit { t: f(0), prim: u(1), inst: u(2), geom: u(3), bary: [f(4), f(5)], kind: u(6), custom: u(7) }
    }

    fn is_hit(&self) -> bool {
        self.kind != 0
    }

    /// A triangle hit within `EDGE_TOL` of an edge.
    fn near_edge(&self) -> bool {
        let [u, v] = self.bary;
        self.kind == 1 && u.min(v).min(1.0 - u - v) < EDGE_TOL
    }
}

/// What differs on one ray. A tie (both hit, t within tolerance, another primitive, instance
/// or geometry) is two equally close answers, both right; an edge case (one side lacks a hit the
/// other found nearest, within `EDGE_TOL` of an edge) is rounding at an open edge. Both are
/// counted; neither is a mismatch.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Diff {
    pub hit_miss: bool,
    pub primitive: bool,
    pub instance: bool,
    pub geometry: bool,
    pub t: bool,
    pub barycentrics: bool,
    pub tie: bool,
    pub edge: bool,
}

impl Diff {
    pub fn is_mismatch(&self) -> bool {
        self.hit_miss || self.primitive || self.instance || self.geometry || self.t || self.barycentrics
    }

    fn names(&self) -> Vec<&'static str> {
        let all = [
            (self.hit_miss, "hit/miss"),
            (self.primitive, "primitive"),
            (self.instance, "instance"),
            (self.geometry, "geometry"),
            (self.t, "t"),
            (self.barycentrics, "barycentrics"),
        ];
        all.iter().filter(|(on, _)| *on).map(|(_, n)| *n).collect()
    }
}

/// |a - b| relative to the scale of the numbers t along `ray` is computed from (see `T_REL_TOL`).
fn t_rel_diff(ray: &TraceRay, a: f32, b: f32) -> f32 {
    let o = ray.origin.iter().fold(0.0f32, |m, c| m.max(c.abs()));
    let d = (ray.dir[0] * ray.dir[0] + ray.dir[1] * ray.dir[1] + ray.dir[2] * ray.dir[2]).sqrt();
    let scale = a.abs().max(b.abs()) + if d > 0.0 { o / d } else { 0.0 };
    if a == b {
        0.0
    } else if scale > 0.0 {
        (a - b).abs() / scale
    } else {
        f32::INFINITY
    }
}

/// Whether `a` and `b` are the same t along `ray` within `T_REL_TOL`.
fn t_close(ray: &TraceRay, a: f32, b: f32) -> bool {
    t_rel_diff(ray, a, b) <= T_REL_TOL
}

/// The rules: hit/miss, primitive, instance (index and custom index) and geometry exact; t within
/// `T_REL_TOL` relative; barycentrics within `BARY_ABS_TOL`, compared only for the same triangle.
pub fn diff(ray: &TraceRay, a: &Hit, b: &Hit) -> Diff {
    let mut d = Diff::default();
    if a.is_hit() != b.is_hit() || a.kind != b.kind {
        let found = if a.is_hit() { a } else { b };
        d.edge = a.is_hit() != b.is_hit() && found.near_edge();
        d.hit_miss = !d.edge;
        return d;
    }
    if !a.is_hit() {
        return d;
    }
    let close = t_close(ray, a.t, b.t);
    let same_triangle = a.prim == b.prim && a.inst == b.inst && a.custom == b.custom && a.geom == b.geom;
    if !same_triangle && close {
        d.tie = true;
        return d;
    }
    if !same_triangle && (if a.t < b.t { a } else { b }).near_edge() {
        d.edge = true;
        return d;
    }
    d.primitive = a.prim != b.prim;
    d.instance = a.inst != b.inst || a.custom != b.custom;
    d.geometry = a.geom != b.geom;
    d.t = !close;
    d.barycentrics = same_triangle
        && (0..2).any(|k| {
            let e = (a.bary[k] - b.bary[k]).abs();
            e.is_nan() || e > BARY_ABS_TOL
        });
    d
}

/// One mismatching ray, both answers.
#[derive(Clone, Debug)]
pub struct Mismatch {
    pub index: usize,
    pub ray: TraceRay,
    pub arbor: Hit,
    pub other: Hit,
    pub diff: Diff,
}

/// The comparison of one scene and workload.
#[derive(Clone, Debug, Default)]
pub struct Comparison {
    pub scene: String,
    pub workload: String,
    pub other: String,
    pub rays: usize,
    pub hits_arbor: usize,
    pub hits_other: usize,
    pub hit_miss: usize,
    pub primitive: usize,
    pub instance: usize,
    pub geometry: usize,
    pub t: usize,
    pub barycentrics: usize,
    pub ties: usize,
    pub edges: usize,
    /// The largest differences among rays where both hit the same triangle: t relative (as
    /// `T_REL_TOL` measures it) and barycentric, absolute (NaN counts as infinite).
    pub max_t_rel: f32,
    pub max_bary: f32,
    /// Rays with any mismatch (ties excluded).
    pub mismatches: usize,
    /// The first `show` mismatching rays.
    pub first: Vec<Mismatch>,
}

/// Arbor's hits `a` against the other driver's `b` for the same `rays`; keeps the first `show`
/// mismatching rays.
pub fn compare(rays: &[TraceRay], a: &[Hit], b: &[Hit], show: usize) -> Comparison {
    let mut c = Comparison { rays: rays.len().min(a.len()).min(b.len()), ..Comparison::default() };
    for (i, ((r, x), y)) in rays.iter().zip(a).zip(b).enumerate() {
        c.hits_arbor += x.is_hit() as usize;
        c.hits_other += y.is_hit() as usize;
        let d = diff(r, x, y);
        c.ties += d.tie as usize;
        c.edges += d.edge as usize;
        c.hit_miss += d.hit_miss as usize;
        c.primitive += d.primitive as usize;
        c.instance += d.instance as usize;
        c.geometry += d.geometry as usize;
        c.t += d.t as usize;
        c.barycentrics += d.barycentrics as usize;
        if x.is_hit() && y.is_hit() && x.prim == y.prim && x.inst == y.inst && x.geom == y.geom {
            c.max_t_rel = c.max_t_rel.max(t_rel_diff(r, x.t, y.t));
            let db = (0..2).map(|k| (x.bary[k] - y.bary[k]).abs()).fold(0.0f32, |m, v| if v.is_nan() { f32::INFINITY } else { m.max(v) });
            c.max_bary = c.max_bary.max(db);
        }
        if d.is_mismatch() {
            c.mismatches += 1;
            if c.first.len() < show {
                c.first.push(Mismatch { index: i, ray: *r, arbor: *x, other: *y, diff: d });
            }
        }
    }
    c
}

fn fmt_hit(h: &Hit) -> String {
    if h.kind == 0 {
        "miss".into()
    } else {
        format!(
            "t {:.9e} prim {} inst {} (custom {}) geom {} bary ({:.7}, {:.7})",
            h.t, h.prim, h.inst, h.custom, h.geom, h.bary[0], h.bary[1]
        )
    }
}

fn fmt_v(v: [f32; 3]) -> String {
    format!("({:.9e}, {:.9e}, {:.9e})", v[0], v[1], v[2])
}

impl Comparison {
    /// The block printed under the table.
    pub fn text(&self) -> String {
        let mut o = String::new();
        let _ = writeln!(
            o,
            "compare arbor vs {} on {} {}: {} rays, hits {} / {}; mismatches {} (hit/miss {}, primitive {}, instance {}, geometry {}, t {}, barycentrics {}); ties {}, edge cases {}; largest t difference {:.1e} (tolerance {:.0e}), barycentric {:.1e} (tolerance {:.0e})",
            self.other,
            self.scene,
            self.workload,
            self.rays,
            self.hits_arbor,
            self.hits_other,
            self.mismatches,
            self.hit_miss,
            self.primitive,
            self.instance,
            self.geometry,
            self.t,
            self.barycentrics,
            self.ties,
            self.edges,
            self.max_t_rel,
            T_REL_TOL,
            self.max_bary,
            BARY_ABS_TOL
        );
        for m in &self.first {
            let _ = writeln!(o, "  ray {} origin {} dir {} [{}]", m.index, fmt_v(m.ray.origin), fmt_v(m.ray.dir), m.diff.names().join(", "));
            let _ = writeln!(o, "    arbor:    {}", fmt_hit(&m.arbor));
            let _ = writeln!(o, "    {:<9} {}", format!("{}:", self.other), fmt_hit(&m.other));
        }
        o
    }

    /// One JSON object (no trailing newline).
    pub fn json(&self) -> String {
        let hit = |h: &Hit| {
            format!(
                "{{\"hit\": {}, \"t\": {}, \"primitive\": {}, \"instance\": {}, \"custom_index\": {}, \"geometry\": {}, \"barycentrics\": [{}, {}]}}",
                h.kind != 0,
                jf(h.t),
                h.prim,
                h.inst,
                h.custom,
                h.geom,
                jf(h.bary[0]),
                jf(h.bary[1])
            )
        };
        let v = |v: [f32; 3]| format!("[{}, {}, {}]", jf(v[0]), jf(v[1]), jf(v[2]));
        let first: Vec<String> = self
            .first
            .iter()
            .map(|m| {
                let what: Vec<String> = m.diff.names().iter().map(|n| json_str(n)).collect();
                format!(
                    "{{\"ray\": {}, \"origin\": {}, \"direction\": {}, \"differs\": [{}], \"arbor\": {}, \"other\": {}}}",
                    m.index,
                    v(m.ray.origin),
                    v(m.ray.dir),
                    what.join(", "),
                    hit(&m.arbor),
                    hit(&m.other)
                )
            })
            .collect();
        format!(
            "{{\"scene\": {}, \"workload\": {}, \"driver\": \"arbor\", \"other\": {}, \"rays\": {}, \"hits_arbor\": {}, \"hits_other\": {}, \
             \"t_rel_tol\": {}, \"bary_abs_tol\": {}, \"mismatches\": {}, \"hit_miss\": {}, \"primitive\": {}, \"instance\": {}, \
             \"geometry\": {}, \"t\": {}, \"barycentrics\": {}, \"ties\": {}, \"edge_cases\": {}, \"edge_tol\": {}, \"max_t_rel_diff\": {}, \"max_bary_diff\": {}, \"first\": [{}]}}",
            json_str(&self.scene),
            json_str(&self.workload),
            json_str(&self.other),
            self.rays,
            self.hits_arbor,
            self.hits_other,
            jf(T_REL_TOL),
            jf(BARY_ABS_TOL),
            self.mismatches,
            self.hit_miss,
            self.primitive,
            self.instance,
            self.geometry,
            self.t,
            self.barycentrics,
            self.ties,
            self.edges,
            jf(EDGE_TOL),
            jf(self.max_t_rel),
            jf(self.max_bary),
            first.join(", ")
        )
    }
}

/// A JSON number for an f32 (exact round trip), null where not finite.
fn jf(x: f32) -> String {
    if x.is_finite() {
        format!("{x:e}")
    } else {
        "null".into()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hit(t: f32, prim: u32) -> Hit {
        Hit { t, prim, inst: 0, geom: 0, bary: [0.25, 0.5], kind: 1, custom: 0 }
    }

    fn rays(n: usize) -> Vec<TraceRay> {
        (0..n).map(|i| TraceRay { origin: [i as f32, 0.0, 0.0], tmin: 0.0, dir: [0.0, 0.0, 1.0], tmax: f32::INFINITY }).collect()
    }

    #[test]
    fn identical_answers_have_no_mismatch() {
        let a = vec![hit(1.0, 3), Hit::default(), hit(2.5, 7)];
        let c = compare(&rays(3), &a, &a.clone(), 10);
        assert_eq!((c.mismatches, c.ties, c.hits_arbor, c.hits_other), (0, 0, 2, 2));
        assert!(c.first.is_empty());
    }

    /// Every category caught on a hand-made answer set, each on its own ray, and the first
    /// mismatching rays kept in order.
    #[test]
    fn each_category_is_caught() {
        let a = vec![hit(1.0, 1), hit(1.0, 2), hit(1.0, 3), hit(1.0, 4), hit(1.0, 5), hit(1.0, 6), hit(1.0, 7), hit(1.0, 8)];
        let mut b = a.clone();
        b[0] = Hit::default(); // miss against hit
        b[1].prim = 99;
        b[1].t = 1.5; // another primitive, farther: not a tie
        b[2].inst = 1;
        b[2].custom = 1;
        b[2].t = 0.5;
        b[3].geom = 1;
        b[3].t = 2.0;
        b[4].t = 1.0 + 1e-3;
        b[5].bary[1] += 1e-1;
        b[6].prim = 42; // same t: a tie
        b[7].t = 1.0 + 1e-7; // within tolerance
        b[7].bary[0] += 1e-3;
        let c = compare(&rays(8), &a, &b, 3);
        assert_eq!(
            (c.hit_miss, c.primitive, c.instance, c.geometry, c.t, c.barycentrics, c.ties),
            (1, 1, 1, 1, 4, 1, 1),
            "{c:?}"
        );
        assert_eq!(c.mismatches, 6);
        assert_eq!(c.first.iter().map(|m| m.index).collect::<Vec<_>>(), vec![0, 1, 2]);
        assert!(c.text().contains("mismatches 6 (hit/miss 1, primitive 1, instance 1, geometry 1, t 4, barycentrics 1); ties 1, edge cases 0"), "{}", c.text());
        // Same triangle on rays 4, 5 and 7: t differs most on 4, barycentrics on 5.
        assert!((c.max_bary - 0.1).abs() < 1e-6 && c.max_t_rel > T_REL_TOL, "{c:?}");
        let j = c.json();
        assert!(j.contains("\"mismatches\": 6") && j.contains("\"differs\": [\"hit/miss\"]") && j.contains("\"ray\": 2"), "{j}");
    }

    /// t's tolerance scales with the coordinates it is computed from: a short hit far from the
    /// world's origin may differ by more than its own relative 1e-5; a far one may not.
    #[test]
    fn t_tolerance_follows_the_origin() {
        let far = [TraceRay { origin: [1000.0, 0.0, 0.0], tmin: 0.0, dir: [0.0, 0.0, 1.0], tmax: f32::INFINITY }];
        let (a, mut b) = (vec![hit(0.006, 1)], vec![hit(0.006, 1)]);
        b[0].t = 0.006 + 1e-4;
        assert_eq!(compare(&far, &a, &b, 1).t, 0);
        b[0].t = 0.006 + 1e-1;
        assert_eq!(compare(&far, &a, &b, 1).t, 1);
        let near = [TraceRay { origin: [0.0; 3], ..far[0] }];
        b[0].t = 0.006 + 1e-4;
        assert_eq!(compare(&near, &a, &b, 1).t, 1);
    }

    /// A hit one side lacks is an edge case only when it lies within EDGE_TOL of an edge; a
    /// nearer hit the other side passed by likewise.
    #[test]
    fn edge_cases_are_near_edges_only() {
        let near = Hit { bary: [0.3, 0.7 - 1e-4], ..hit(1.0, 1) };
        let inside = Hit { bary: [0.2, 0.3], ..hit(1.0, 1) };
        let far = hit(2.0, 2);
        let c = compare(&rays(4), &[near, inside, near, inside], &[Hit::default(), Hit::default(), far, far], 4);
        assert_eq!((c.edges, c.hit_miss, c.primitive, c.mismatches), (2, 1, 1, 2), "{c:?}");
        assert_eq!(c.first.iter().map(|m| m.index).collect::<Vec<_>>(), vec![1, 3]);
    }

    #[test]
    fn nan_barycentrics_are_a_mismatch() {
        let a = vec![hit(1.0, 1)];
        let mut b = a.clone();
        b[0].bary[0] = f32::NAN;
        assert_eq!(compare(&rays(1), &a, &b, 1).barycentrics, 1);
    }

    #[test]
    fn bytes_round_trip() {
        let h = Hit { t: 3.5, prim: 7, inst: 2, geom: 1, bary: [0.125, 0.75], kind: 1, custom: 9 };
        let mut b = Vec::new();
        for w in [h.t.to_bits(), h.prim, h.inst, h.geom, h.bary[0].to_bits(), h.bary[1].to_bits(), h.kind, h.custom] {
            b.extend_from_slice(&w.to_le_bytes());
        }
        assert_eq!(Hit::from_bytes(&b), h);
        let r = TraceRay { origin: [1.0, 2.0, 3.0], tmin: 0.0, dir: [0.0, 1.0, 0.0], tmax: 9.0 };
        assert_eq!(f32::from_le_bytes(r.to_bytes()[28..32].try_into().unwrap()), 9.0);
    }
}
