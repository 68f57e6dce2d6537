//! Output: the aligned terminal table, JSON and CSV written by hand, and an SVG chart.
use std::fmt::Write as _;

use crate::work::{Row, Stats, Status};

/// Columns of the terminal table, in order (tests check every one is there).
pub const TABLE_COLUMNS: [&str; 19] = [
    "driver", "threads", "scene", "workload", "prims", "timing", "median ms", "min ms", "max ms", "wall ms", "Mprim/s", "AS size",
    "compacted", "scratch", "B/prim", "SAH", "nodes", "leaves", "Mray/s",
];

/// Keys of each JSON result object and CSV columns, in order.
pub const FIELDS: [&str; 27] = [
    "driver", "device", "threads", "scene", "workload", "primitives", "status", "reason", "timing", "repeat", "median_ms", "min_ms",
    "max_ms", "wall_median_ms", "wall_min_ms", "wall_max_ms", "mprims_per_s", "as_size", "compacted_size", "scratch_size",
    "bytes_per_prim", "sah_cost", "node_count", "leaf_count", "note", "rays", "mrays_per_s",
];

pub fn fmt_bytes(b: u64) -> String {
    if b >= 1 << 30 {
        format!("{:.2} GiB", b as f64 / (1u64 << 30) as f64)
    } else if b >= 1 << 20 {
        format!("{:.2} MiB", b as f64 / (1u64 << 20) as f64)
    } else if b >= 1 << 10 {
        format!("{:.1} KiB", b as f64 / 1024.0)
    } else {
        format!("{b} B")
    }
}

fn fmt_ms(v: f64) -> String {
    if v >= 100.0 {
        format!("{v:.1}")
    } else if v >= 1.0 {
        format!("{v:.2}")
    } else {
        format!("{v:.3}")
    }
}

pub fn bytes_per_prim(r: &Row) -> Option<f64> {
    let b = r.compacted_size.unwrap_or(r.as_size);
    (r.status == Status::Ok && b > 0 && r.primitives > 0 && r.rays == 0).then(|| b as f64 / r.primitives as f64)
}

fn cells(r: &Row) -> Vec<String> {
    let dash = || "-".to_string();
    let mut c = vec![r.driver.clone(), r.threads.clone(), r.scene.clone(), r.workload.clone(), r.primitives.to_string()];
    match &r.status {
        Status::Ok => {
            let t = r.time.unwrap_or(Stats { median: 0.0, min: 0.0, max: 0.0 });
            c.push(r.timing.to_string());
            c.push(fmt_ms(t.median));
            c.push(fmt_ms(t.min));
            c.push(fmt_ms(t.max));
            c.push(r.wall.map(|w| fmt_ms(w.median)).unwrap_or_else(dash));
            c.push(r.mprims_per_s().map(|m| format!("{m:.2}")).unwrap_or_else(dash));
            c.push(fmt_bytes(r.as_size));
            c.push(r.compacted_size.map(fmt_bytes).unwrap_or_else(dash));
            c.push(if r.scratch_size > 0 { fmt_bytes(r.scratch_size) } else { dash() });
            c.push(bytes_per_prim(r).map(|b| format!("{b:.1}")).unwrap_or_else(dash));
            c.push(r.sah.map(|s| format!("{s:.2}")).unwrap_or_else(dash));
            c.push(r.nodes.map(|s| s.to_string()).unwrap_or_else(dash));
            c.push(r.leaves.map(|s| s.to_string()).unwrap_or_else(dash));
            c.push(r.mrays_per_s().map(|m| format!("{m:.3}")).unwrap_or_else(dash));
        }
        Status::NotSupported(_) | Status::Failed(_) => {
            c.push(dash());
            c.push(if matches!(r.status, Status::Failed(_)) { "FAILED".into() } else { "not supported".into() });
            while c.len() < TABLE_COLUMNS.len() {
                c.push(dash());
            }
        }
    }
    c
}

/// The aligned table, with the reasons for unsupported/failed rows listed below it.
pub fn table(rows: &[Row]) -> String {
    let mut all: Vec<Vec<String>> = vec![TABLE_COLUMNS.iter().map(|s| s.to_string()).collect()];
    all.extend(rows.iter().map(cells));
    let n = TABLE_COLUMNS.len();
    let widths: Vec<usize> = (0..n).map(|k| all.iter().map(|r| r[k].chars().count()).max().unwrap_or(0)).collect();
    let left = |k: usize| k < 4 || k == 5;
    let mut out = String::new();
    for (i, r) in all.iter().enumerate() {
        let mut line = String::new();
        for k in 0..n {
            if k > 0 {
                line.push_str("  ");
            }
            let pad = widths[k] - r[k].chars().count();
            if left(k) {
                line.push_str(&r[k]);
                line.push_str(&" ".repeat(pad));
            } else {
                line.push_str(&" ".repeat(pad));
                line.push_str(&r[k]);
            }
        }
        out.push_str(line.trim_end());
        out.push('\n');
        if i == 0 {
            out.push_str(&"-".repeat(widths.iter().sum::<usize>() + 2 * (n - 1)));
            out.push('\n');
        }
    }
    let mut notes: Vec<String> = Vec::new();
    for r in rows {
        let s = match &r.status {
            Status::NotSupported(why) => format!("{}: {} not supported ({why})", r.driver, r.workload),
            Status::Failed(why) => format!("{} {} {}: FAILED: {why}", r.driver, r.scene, r.workload),
            Status::Ok => continue,
        };
        if !notes.contains(&s) {
            notes.push(s);
        }
    }
    for s in notes {
        out.push_str(&s);
        out.push('\n');
    }
    // Compute rows: their rate in invocations and how the result was verified.
    for r in rows.iter().filter(|r| r.status == Status::Ok && r.workload.starts_with("compute-")) {
        let _ = writeln!(out, "{} (threads {}) {}: {}", r.driver, r.threads, r.workload, r.note);
    }
    out
}

pub fn json_str(s: &str) -> String {
    let mut o = String::with_capacity(s.len() + 2);
    o.push('"');
    for ch in s.chars() {
        match ch {
            '"' => o.push_str("\\\""),
            '\\' => o.push_str("\\\\"),
            '\n' => o.push_str("\\n"),
            '\r' => o.push_str("\\r"),
            '\t' => o.push_str("\\t"),
            c if (c as u32) < 0x20 => {
                let _ = write!(o, "\\u{:04x}", c as u32);
            }
            c => o.push(c),
        }
    }
    o.push('"');
    o
}

fn num(v: Option<f64>) -> String {
    match v {
        Some(x) if x.is_finite() => {
            let s = format!("{x:.6}");
            let s = s.trim_end_matches('0').trim_end_matches('.').to_string();
            if s.is_empty() || s == "-" {
                "0".into()
            } else {
                s
            }
        }
        _ => "null".into(),
    }
}

/// Values of FIELDS for one row: (json literal, csv cell).
fn values(r: &Row) -> Vec<(String, String)> {
    let s = |v: &str| (json_str(v), csv_cell(v));
    let n = |v: Option<f64>| {
        let j = num(v);
        let c = if j == "null" { String::new() } else { j.clone() };
        (j, c)
    };
    let ok = r.status == Status::Ok;
    let t = if ok { r.time } else { None };
    let w = if ok { r.wall } else { None };
    let (status, reason) = match &r.status {
        Status::Ok => ("ok", String::new()),
        Status::NotSupported(x) => ("not supported", x.clone()),
        Status::Failed(x) => ("failed", x.clone()),
    };
    let u = |v: u64| n(ok.then_some(v as f64));
    vec![
        s(&r.driver),
        s(&r.device),
        s(&r.threads),
        s(&r.scene),
        s(&r.workload),
        n(Some(r.primitives as f64)),
        s(status),
        s(&reason),
        s(if ok { r.timing } else { "" }),
        n(Some(r.repeat as f64)),
        n(t.map(|t| t.median)),
        n(t.map(|t| t.min)),
        n(t.map(|t| t.max)),
        n(w.map(|t| t.median)),
        n(w.map(|t| t.min)),
        n(w.map(|t| t.max)),
        n(if ok { r.mprims_per_s() } else { None }),
        u(r.as_size),
        n(if ok { r.compacted_size.map(|v| v as f64) } else { None }),
        u(r.scratch_size),
        n(bytes_per_prim(r)),
        n(r.sah),
        n(r.nodes.map(|v| v as f64)),
        n(r.leaves.map(|v| v as f64)),
        s(&r.note),
        n((r.rays > 0).then_some(r.rays as f64)),
        n(if ok { r.mrays_per_s() } else { None }),
    ]
}

fn csv_cell(v: &str) -> String {
    if v.contains([',', '"', '\n']) {
        format!("\"{}\"", v.replace('"', "\"\""))
    } else {
        v.to_string()
    }
}

pub struct Meta {
    pub command: String,
    pub unix_time: u64,
    pub host_cpus: usize,
    /// (label, device, driver version, host commands, indirect builds, timestamps)
    pub drivers: Vec<(String, String, String, bool, bool, bool)>,
    /// (name, primitives, description)
    pub scenes: Vec<(String, u64, String)>,
}

/// The JSON report with extra top-level arrays after "results": (key, preformatted objects).
pub fn json_with(meta: &Meta, rows: &[Row], extra: &[(&str, Vec<String>)]) -> String {
    let mut o = json(meta, rows);
    if extra.is_empty() {
        return o;
    }
    o.truncate(o.len() - "\n}\n".len());
    for (key, objects) in extra {
        let _ = write!(o, ",\n  {}: [", json_str(key));
        for (i, obj) in objects.iter().enumerate() {
            o.push_str(if i == 0 { "\n    " } else { ",\n    " });
            o.push_str(obj);
        }
        o.push_str(if objects.is_empty() { "]" } else { "\n  ]" });
    }
    o.push_str("\n}\n");
    o
}

pub fn json(meta: &Meta, rows: &[Row]) -> String {
    let mut o = String::new();
    o.push_str("{\n");
    let _ = writeln!(o, "  \"tool\": \"arbor-bench\",");
    let _ = writeln!(o, "  \"command\": {},", json_str(&meta.command));
    let _ = writeln!(o, "  \"unix_time\": {},", meta.unix_time);
    let _ = writeln!(o, "  \"host_cpus\": {},", meta.host_cpus);
    o.push_str("  \"drivers\": [\n");
    for (i, d) in meta.drivers.iter().enumerate() {
        let _ = write!(
            o,
            "    {{\"label\": {}, \"device\": {}, \"driver_version\": {}, \"host_commands\": {}, \"indirect_build\": {}, \"timestamps\": {}}}",
            json_str(&d.0),
            json_str(&d.1),
            json_str(&d.2),
            d.3,
            d.4,
            d.5
        );
        o.push_str(if i + 1 < meta.drivers.len() { ",\n" } else { "\n" });
    }
    o.push_str("  ],\n  \"scenes\": [\n");
    for (i, s) in meta.scenes.iter().enumerate() {
        let _ = write!(o, "    {{\"name\": {}, \"primitives\": {}, \"description\": {}}}", json_str(&s.0), s.1, json_str(&s.2));
        o.push_str(if i + 1 < meta.scenes.len() { ",\n" } else { "\n" });
    }
    o.push_str("  ],\n  \"results\": [\n");
    for (i, r) in rows.iter().enumerate() {
        let v = values(r);
        o.push_str("    {");
        for (k, (f, (j, _))) in FIELDS.iter().zip(v).enumerate() {
            if k > 0 {
                o.push_str(", ");
            }
            let _ = write!(o, "\"{f}\": {j}");
        }
        o.push('}');
        o.push_str(if i + 1 < rows.len() { ",\n" } else { "\n" });
    }
    o.push_str("  ]\n}\n");
    o
}

pub fn csv(rows: &[Row]) -> String {
    let mut o = FIELDS.join(",");
    o.push('\n');
    for r in rows {
        let cells: Vec<String> = values(r).into_iter().map(|(_, c)| c).collect();
        o.push_str(&cells.join(","));
        o.push('\n');
    }
    o
}

fn esc(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;").replace('"', "&quot;")
}

const PALETTE: [&str; 8] = ["#2e7d32", "#c62828", "#1565c0", "#ef6c00", "#6a1b9a", "#00838f", "#5d4037", "#455a64"];

/// Two grouped bar charts: device build time (PREFER_FAST_TRACE and PREFER_FAST_BUILD median,
/// log scale) and compacted bytes per primitive (fast-trace build), by scene and driver.
pub fn svg(rows: &[Row], title: &str) -> String {
    let mut drivers: Vec<String> = Vec::new();
    let mut scenes: Vec<String> = Vec::new();
    for r in rows {
        let d = series_key(r);
        if !drivers.contains(&d) {
            drivers.push(d);
        }
        if !scenes.contains(&r.scene) {
            scenes.push(r.scene.clone());
        }
    }
    let c = Chart { rows, drivers, scenes, pw: 520.0, ph: 300.0, ml: 60.0, mt: 50.0, mb: 60.0 };
    let width = c.ml + c.pw + 90.0 + c.pw + 30.0;
    let legend_h = 20.0 * c.drivers.len() as f64 + 30.0;
    let height = c.mt + c.ph + c.mb + legend_h;
    let mut o = String::new();
    let _ = writeln!(
        o,
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{width:.0}\" height=\"{height:.0}\" viewBox=\"0 0 {width:.0} {height:.0}\" font-family=\"sans-serif\" font-size=\"12\">"
    );
    let _ = writeln!(o, "<rect width=\"100%\" height=\"100%\" fill=\"white\"/>");
    let _ = writeln!(o, "<text x=\"{:.0}\" y=\"22\" font-size=\"15\" font-weight=\"bold\">{}</text>", c.ml, esc(title));
    c.time_panel(&mut o);
    c.size_panel(&mut o);
    c.legend(&mut o);
    o.push_str("</svg>\n");
    o
}

/// A driver in the chart: its label, with its thread count where it has one.
fn series_key(r: &Row) -> String {
    if r.threads.is_empty() || r.threads == "-" {
        r.driver.clone()
    } else {
        format!("{} ({} thr)", r.driver, r.threads)
    }
}

/// The chart's rows, its drivers and scenes in first-seen order, and its layout: panel width and
/// height, left, top and bottom margins.
struct Chart<'r> {
    rows: &'r [Row],
    drivers: Vec<String>,
    scenes: Vec<String>,
    pw: f64,
    ph: f64,
    ml: f64,
    mt: f64,
    mb: f64,
}

impl Chart<'_> {
    fn find(&self, d: &str, s: &str, w: &str) -> Option<&Row> {
        self.rows.iter().find(|r| series_key(r) == d && r.scene == s && r.workload == w && r.status == Status::Ok)
    }

    /// Width of one scene's group of bars.
    fn group_width(&self) -> f64 {
        self.pw / self.scenes.len().max(1) as f64
    }

    /// Scene `si`'s label under its group of bars, in the panel starting at `x0`.
    fn scene_label(&self, o: &mut String, x0: f64, si: usize, s: &str) {
        let gw = self.group_width();
        let _ = writeln!(o, "<text x=\"{:.1}\" y=\"{:.0}\" text-anchor=\"middle\">{}</text>", x0 + si as f64 * gw + gw / 2.0, self.mt + self.ph + 18.0, esc(s));
    }

    /// The axes of the panel starting at `x0`.
    fn axes(&self, o: &mut String, x0: f64) {
        let (ph, mt) = (self.ph, self.mt);
        let _ = writeln!(o, "<line x1=\"{x0:.0}\" x2=\"{x0:.0}\" y1=\"{mt:.0}\" y2=\"{:.0}\" stroke=\"black\"/>", mt + ph);
        let _ = writeln!(o, "<line x1=\"{x0:.0}\" x2=\"{:.0}\" y1=\"{:.0}\" y2=\"{:.0}\" stroke=\"black\"/>", x0 + self.pw, mt + ph, mt + ph);
    }

    /// Panel 1: build time, log10 scale; per driver a fast-trace (solid) and fast-build (light) bar.
    fn time_panel(&self, o: &mut String) {
        let (pw, ph, mt) = (self.pw, self.ph, self.mt);
        let series: Vec<(String, usize, &str)> = self
            .drivers
            .iter()
            .enumerate()
            .flat_map(|(i, d)| [(d.clone(), i, "fast-trace"), (d.clone(), i, "fast-build")])
            .collect();
        let median = |d: &str, s: &str, w: &str| self.find(d, s, w).and_then(|r| r.time).map(|t| t.median).filter(|t| *t > 0.0);
        let times: Vec<f64> = series.iter().flat_map(|(d, _, w)| self.scenes.iter().filter_map(move |s| median(d, s, w))).collect();
        let lo = times.iter().cloned().fold(f64::INFINITY, f64::min);
        let hi = times.iter().cloned().fold(0.0f64, f64::max);
        let (e0, e1) = if times.is_empty() { (-1, 3) } else { (lo.log10().floor() as i32, (hi.log10().ceil() as i32).max(lo.log10().floor() as i32 + 1)) };
        let x0 = self.ml;
        let y_of = |t: f64| mt + ph - (t.log10() - e0 as f64) / (e1 - e0) as f64 * ph;
        let _ = writeln!(o, "<text x=\"{x0:.0}\" y=\"{:.0}\" font-weight=\"bold\">Device build time, ms (log scale; solid = fast-trace, light = fast-build)</text>", mt - 12.0);
        for e in e0..=e1 {
            let y = mt + ph - (e - e0) as f64 / (e1 - e0) as f64 * ph;
            let _ = writeln!(o, "<line x1=\"{x0:.0}\" x2=\"{:.0}\" y1=\"{y:.1}\" y2=\"{y:.1}\" stroke=\"#ddd\"/>", x0 + pw);
            let label = format!("{}", 10f64.powi(e));
            let _ = writeln!(o, "<text x=\"{:.0}\" y=\"{:.1}\" text-anchor=\"end\">{label}</text>", x0 - 6.0, y + 4.0);
        }
        let gw = self.group_width();
        let bw = (gw * 0.8) / series.len().max(1) as f64;
        for (si, s) in self.scenes.iter().enumerate() {
            let gx = x0 + si as f64 * gw + gw * 0.1;
            for (k, (d, di, w)) in series.iter().enumerate() {
                if let Some(t) = median(d, s, w) {
                    let y = y_of(t).min(mt + ph);
                    let op = if *w == "fast-trace" { "1" } else { "0.5" };
                    let _ = writeln!(
                        o,
                        "<rect x=\"{:.1}\" y=\"{y:.1}\" width=\"{:.1}\" height=\"{:.1}\" fill=\"{}\" fill-opacity=\"{op}\"><title>{} {} {}: {:.3} ms</title></rect>",
                        gx + k as f64 * bw,
                        bw * 0.92,
                        mt + ph - y,
                        PALETTE[di % PALETTE.len()],
                        esc(d),
                        esc(s),
                        w,
                        t
                    );
                }
            }
            self.scene_label(o, x0, si, s);
        }
        self.axes(o, x0);
    }

    /// Panel 2: compacted bytes per primitive of the fast-trace build, linear.
    fn size_panel(&self, o: &mut String) {
        let (pw, ph, mt) = (self.pw, self.ph, self.mt);
        let x1 = self.ml + pw + 90.0;
        let per_prim = |d: &str, s: &str| self.find(d, s, "fast-trace").and_then(bytes_per_prim);
        let vals: Vec<f64> = self.drivers.iter().flat_map(|d| self.scenes.iter().filter_map(move |s| per_prim(d, s))).collect();
        let vmax = vals.iter().cloned().fold(0.0f64, f64::max).max(1.0);
        let step = [1.0, 2.0, 5.0, 10.0, 20.0, 25.0, 50.0, 100.0, 200.0, 500.0, 1000.0].into_iter().find(|s| vmax / s <= 8.0).unwrap_or(1000.0);
        let top = (vmax / step).ceil() * step;
        let _ = writeln!(o, "<text x=\"{x1:.0}\" y=\"{:.0}\" font-weight=\"bold\">Compacted size, bytes per primitive (fast-trace)</text>", mt - 12.0);
        let mut v = 0.0;
        while v <= top + 1e-9 {
            let y = mt + ph - v / top * ph;
            let _ = writeln!(o, "<line x1=\"{x1:.0}\" x2=\"{:.0}\" y1=\"{y:.1}\" y2=\"{y:.1}\" stroke=\"#ddd\"/>", x1 + pw);
            let _ = writeln!(o, "<text x=\"{:.0}\" y=\"{:.1}\" text-anchor=\"end\">{v}</text>", x1 - 6.0, y + 4.0);
            v += step;
        }
        let gw = self.group_width();
        let bw2 = (gw * 0.8) / self.drivers.len().max(1) as f64;
        for (si, s) in self.scenes.iter().enumerate() {
            let gx = x1 + si as f64 * gw + gw * 0.1;
            for (di, d) in self.drivers.iter().enumerate() {
                if let Some(b) = per_prim(d, s) {
                    let hgt = b / top * ph;
                    let _ = writeln!(
                        o,
                        "<rect x=\"{:.1}\" y=\"{:.1}\" width=\"{:.1}\" height=\"{hgt:.1}\" fill=\"{}\"><title>{} {}: {:.1} B/prim</title></rect>",
                        gx + di as f64 * bw2,
                        mt + ph - hgt,
                        bw2 * 0.92,
                        PALETTE[di % PALETTE.len()],
                        esc(d),
                        esc(s),
                        b
                    );
                }
            }
            self.scene_label(o, x1, si, s);
        }
        self.axes(o, x1);
    }

    /// One swatch and label per driver, under the panels.
    fn legend(&self, o: &mut String) {
        let ml = self.ml;
        for (di, d) in self.drivers.iter().enumerate() {
            let y = self.mt + self.ph + self.mb + 20.0 * di as f64;
            let _ = writeln!(o, "<rect x=\"{ml:.0}\" y=\"{:.0}\" width=\"14\" height=\"14\" fill=\"{}\"/>", y - 11.0, PALETTE[di % PALETTE.len()]);
            let _ = writeln!(o, "<text x=\"{:.0}\" y=\"{y:.0}\">{}</text>", ml + 20.0, esc(d));
        }
    }
}
