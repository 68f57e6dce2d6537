//! Storage-image tests of the library: tests/shaders/image_rw.comp for every format and
//! dimensionality (1D, 2D, 3D, 1D array, 2D array), compiled by glslang and through
//! `spirv-opt -O`, run over `HostMemory` and checked against a CPU reference of the format
//! conversions written here; plus robustness (outside reads give zero, outside writes are
//! dropped and reported) and an unbound image.
use super::tests::compile_with;
use super::*;

/// (IMG prefix, FMT, T, KIND, format): KIND 0 uint, 1 int, 2 float.
const FORMATS: &[(&str, &str, &str, u32, ImageFormat)] = &[
    ("u", "r32ui", "uvec4", 0, ImageFormat::R32Uint),
    ("i", "r32i", "ivec4", 1, ImageFormat::R32Sint),
    ("", "r32f", "vec4", 2, ImageFormat::R32Sfloat),
    ("u", "rgba32ui", "uvec4", 0, ImageFormat::Rgba32Uint),
    ("i", "rgba32i", "ivec4", 1, ImageFormat::Rgba32Sint),
    ("", "rgba32f", "vec4", 2, ImageFormat::Rgba32Sfloat),
    ("", "rgba8", "vec4", 2, ImageFormat::Rgba8Unorm),
];

/// (DIM, image type suffix, invocation grid = extent and layers laid out as x, y, z).
const DIMS: &[(u32, &str, [u32; 3])] = &[
    (1, "1D", [13, 1, 1]),
    (2, "2D", [5, 3, 1]),
    (3, "3D", [5, 3, 2]),
    (4, "1DArray", [6, 3, 1]),
    (5, "2DArray", [5, 3, 3]),
];

/// The view geometry (extent, layers) of a grid for DIM.
fn geometry(dim: u32, grid: [u32; 3]) -> ([u32; 3], u32) {
    match dim {
        4 => ([grid[0], 1, 1], grid[1]),
        5 => ([grid[0], grid[1], 1], grid[2]),
        _ => (grid, 1),
    }
}

/// Deterministic texel bytes; float formats get finite values.
fn source(format: ImageFormat, texels: usize) -> Vec<u8> {
    let mut s = 0x9e37_79b9u32;
    let mut out = Vec::new();
    for i in 0..texels * format.texel_size() as usize / 4 {
        s ^= s << 13;
        s ^= s >> 17;
        s ^= s << 5;
        let w = match format {
            ImageFormat::R32Sfloat | ImageFormat::Rgba32Sfloat => ((s % 2001) as f32 / 8.0 - 125.0).to_bits(),
            _ => s.wrapping_add(i as u32),
        };
        out.extend_from_slice(&w.to_le_bytes());
    }
    out
}

/// CPU reference of `op` in image_rw.comp on one texel, with the format's conversions: only
/// the channels the format stores survive the write.
fn reference(format: ImageFormat, src: &[u8]) -> Vec<u8> {
    let w = |k: usize| u32::from_le_bytes(src[4 * k..4 * k + 4].try_into().unwrap());
    let channels = if format.texel_size() == 16 { 4 } else { 1 };
    match format {
        ImageFormat::Rgba8Unorm => src
            .iter()
            .map(|&b| {
                let f = (b as f32 / 255.0) * 0.5 + 0.25;
                (f.clamp(0.0, 1.0) * 255.0).round() as u8
            })
            .collect(),
        ImageFormat::R32Uint | ImageFormat::Rgba32Uint => {
            (0..channels).flat_map(|k| w(k).wrapping_mul(3).wrapping_add(k as u32 + 1).to_le_bytes()).collect()
        }
        ImageFormat::R32Sint | ImageFormat::Rgba32Sint => {
            let c = [5i32, -6, 7, -8];
            (0..channels).flat_map(|k| c[k].wrapping_sub(w(k) as i32).to_le_bytes()).collect()
        }
        _ => (0..channels).flat_map(|k| (f32::from_bits(w(k)) * 0.5 + 0.25).to_bits().to_le_bytes()).collect(),
    }
}

fn defines(prefix: &str, fmt: &str, t: &str, kind: u32, dim: u32, suffix: &str, extra: &[String]) -> Vec<String> {
    let mut d = vec![format!("IMG={prefix}image{suffix}"), format!("FMT={fmt}"), format!("T={t}"), format!("DIM={dim}"), format!("KIND={kind}")];
    d.extend_from_slice(extra);
    d
}

/// Images sit at offset 64 of their buffers with 64 guard bytes after them.
const GUARD: usize = 64;
const GUARD_BYTE: u8 = 0xA5;

struct Run {
    dst: Vec<u8>,
    size: [i32; 4],
    report: DispatchReport,
}

fn run_image(words: &[u32], format: ImageFormat, dim: u32, grid: [u32; 3], src: &[u8], groups: [u32; 3]) -> Run {
    let module = Module::parse(words).unwrap_or_else(|e| panic!("parse: {e}"));
    let p = Pipeline::compute(&module, "main", &[]).unwrap_or_else(|e| panic!("pipeline: {e}"));
    let (extent, layers) = geometry(dim, grid);
    let mut mem = HostMemory::new();
    let wrap = |body: &[u8]| [vec![GUARD_BYTE; GUARD], body.to_vec(), vec![GUARD_BYTE; GUARD]].concat();
    let a = mem.add_buffer(&wrap(src));
    let b = mem.add_buffer(&wrap(&vec![0u8; src.len()]));
    let s = mem.add_buffer(&[0u8; 16]);
    mem.bind_image(0, 0, ImageBinding::packed(a as u64, GUARD as u64, format, extent, layers));
    mem.bind_image(0, 1, ImageBinding::packed(b as u64, GUARD as u64, format, extent, layers));
    mem.bind(0, 2, s);
    let report = dispatch(&p, &mem, &[], groups, [0; 3], &Watchdog::default());
    let dst = mem.bytes(b);
    assert!(dst[..GUARD].iter().chain(&dst[GUARD + src.len()..]).all(|&g| g == GUARD_BYTE), "guard bytes written");
    let size = mem.bytes(s).chunks(4).map(|c| i32::from_le_bytes(c.try_into().unwrap())).collect::<Vec<_>>();
    Run { dst: dst[GUARD..GUARD + src.len()].to_vec(), size: size.try_into().unwrap(), report }
}

fn expected_size(dim: u32, grid: [u32; 3]) -> [i32; 4] {
    let n = match dim {
        1 => 1,
        2 | 4 => 2,
        _ => 3,
    };
    std::array::from_fn(|k| if k < n { grid[k] as i32 } else { 0 })
}

#[test]
fn load_store_size_every_format_and_dimensionality() {
    for &(prefix, fmt, t, kind, format) in FORMATS {
        for &(dim, suffix, grid) in DIMS {
            let texels = (grid[0] * grid[1] * grid[2]) as usize;
            let src = source(format, texels);
            let ts = format.texel_size() as usize;
            let want: Vec<u8> = src.chunks(ts).flat_map(|t| reference(format, t)).collect();
            let defs = defines(prefix, fmt, t, kind, dim, suffix, &[]);
            let defs: Vec<&str> = defs.iter().map(String::as_str).collect();
            let groups = [grid[0].div_ceil(4), grid[1].div_ceil(2), grid[2]];
            for (what, words) in compile_with("image_rw.comp", &defs) {
                let r = run_image(&words, format, dim, grid, &src, groups);
                assert!(r.report.is_clean(), "{what} {fmt} {suffix}: {:?}", r.report);
                assert_eq!(r.size, expected_size(dim, grid), "{what} {fmt} {suffix}: imageSize");
                assert_eq!(r.dst, want, "{what} {fmt} {suffix}: texels");
            }
        }
    }
}

#[test]
fn outside_accesses_read_zero_drop_writes_and_fault() {
    // 2D r32ui 5x3 with a 2x2-group dispatch of 4x2 invocations: 8x4 invocations, 15 inside.
    let (grid, format) = ([5, 3, 1], ImageFormat::R32Uint);
    let src = source(format, 15);
    let extra = ["NOGUARD".to_string()];
    let defs = defines("u", "r32ui", "uvec4", 0, 2, "2D", &extra);
    let defs: Vec<&str> = defs.iter().map(String::as_str).collect();
    for (what, words) in compile_with("image_rw.comp", &defs) {
        let r = run_image(&words, format, 2, grid, &src, [2, 2, 1]);
        let want: Vec<u8> = src.chunks(4).flat_map(|t| reference(format, t)).collect();
        assert_eq!(r.dst, want, "{what}: inside texels");
        // 17 invocations outside: one read and one write fault each.
        assert_eq!(r.report.fault_count, 34, "{what}: {:?}", r.report);
        let f = r.report.faults[0];
        assert_eq!((f.kind, f.space), (FaultKind::OutOfBounds, FaultSpace::Binding { set: 0, binding: 0 }), "{what}");
        assert!(r.report.faults.iter().any(|f| f.write && f.space == FaultSpace::Binding { set: 0, binding: 1 }), "{what}");
    }
}

#[test]
fn unbound_image_faults_and_reads_zero() {
    let defs = defines("", "r32f", "vec4", 2, 2, "2D", &[]);
    let defs: Vec<&str> = defs.iter().map(String::as_str).collect();
    for (what, words) in compile_with("image_rw.comp", &defs) {
        let module = Module::parse(&words).unwrap();
        let p = Pipeline::compute(&module, "main", &[]).unwrap();
        let mut mem = HostMemory::new();
        let s = mem.add_buffer(&[0xFFu8; 16]);
        mem.bind(0, 2, s);
        let report = dispatch(&p, &mem, &[], [1, 1, 1], [0; 3], &Watchdog::default());
        assert!(report.fault_count > 0 && report.faults.iter().all(|f| f.kind == FaultKind::Unbound), "{what}: {report:?}");
        assert_eq!(mem.bytes(s), vec![0u8; 16], "{what}: imageSize of an unbound image reads zero");
    }
}

#[test]
fn sampled_images_are_rejected_at_pipeline_creation() {
    let src = "#version 450\nlayout(local_size_x = 1) in;\n#extension GL_EXT_samplerless_texture_functions : require\nlayout(set = 0, binding = 0) uniform texture2D tex;\nlayout(set = 0, binding = 1, r32f) uniform image2D img;\nvoid main() { imageStore(img, ivec2(0), texelFetch(tex, ivec2(0), 0)); }\n";
    let dir = std::env::temp_dir().join(format!("arbor-image-tests-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (glsl, spv) = (dir.join("arr.comp"), dir.join("arr.spv"));
    std::fs::write(&glsl, src).unwrap();
    let out = std::process::Command::new("glslangValidator").args(["-V", "--target-env", "vulkan1.2", "-o"]).arg(&spv).arg(&glsl).output().unwrap();
    assert!(out.status.success());
    let bytes = std::fs::read(&spv).unwrap();
    let words: Vec<u32> = bytes.chunks(4).map(|c| u32::from_le_bytes(c.try_into().unwrap())).collect();
    // A 2D sampled image (Sampled = 1) is refused where its type is read.
    let err = Module::parse(&words).and_then(|m| Pipeline::compute(&m, "main", &[]).map(|_| ())).unwrap_err();
    assert!(err.to_string().contains("storage image"), "{err}");
}
