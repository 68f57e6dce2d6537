use super::*;
use std::io::Write;

fn data(name: &str) -> std::path::PathBuf {
    // The meshes live in the workspace root's data/ (one copy for the driver's tests, the benches and these).
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../data").join(name)
}

#[test]
fn bunny_counts_and_corners() {
    // data/bunny.ply is the reduced bunny (npm `bunny`), 1,839 vertices / 3,674 triangles,
    // not the 35,947 / 69,451 of the full Stanford scan.
    let text = std::fs::read_to_string(data("bunny.ply")).unwrap();
    let body_lines = text.lines().skip_while(|l| l.trim() != "end_header").skip(1).count();
    let m = load(data("bunny.ply")).unwrap();
    assert_eq!(m.positions.len(), 1839);
    assert_eq!(m.indices.len(), 3674);
    assert_eq!(body_lines, m.positions.len() + m.indices.len());
    assert_eq!(m.positions[0], [1.301895, 0.122622, 2.550061]);
    assert_eq!(*m.indices.last().unwrap(), [816, 589, 1838]);
    assert!(m.max_index() < 1839);
}

#[test]
fn dragon_res4_gzip() {
    let m = load(data("dragon_vrip_res4.ply.gz")).unwrap();
    assert_eq!(m.positions.len(), 5205);
    assert_eq!(m.indices.len(), 11102);
    assert_eq!(m.positions[0], [0.0317083, 0.0557939, -0.049836]);
    let b = m.bounds();
    // The dragon is about 0.2 units wide, centred near the origin.
    assert!(b[0] > -0.2 && b[3] < 0.2 && b[3] - b[0] > 0.1, "{b:?}");
}

#[test]
fn gzip_detected_by_magic_not_name() {
    let src = b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n";
    let mut enc = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
    enc.write_all(src).unwrap();
    let gz = enc.finish().unwrap();
    let dir = std::env::temp_dir().join(format!("arbor-scene-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let p = dir.join("tri.ply"); // gzip content without .gz in the name
    std::fs::write(&p, &gz).unwrap();
    let m = load(&p).unwrap();
    assert_eq!(m.positions, vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]);
    assert_eq!(m.indices, vec![[0, 1, 2]]);
    let p2 = dir.join("noext");
    std::fs::write(&p2, src).unwrap();
    assert_eq!(load(&p2).unwrap(), m);
    std::fs::remove_dir_all(&dir).ok();
}

/// A mesh with a quad, a pentagon and a triangle, and extra properties around x/y/z.
fn poly_fixture() -> (Vec<[f32; 3]>, Vec<Vec<u32>>) {
    let pos: Vec<[f32; 3]> = (0..8).map(|i| [i as f32 * 0.5, -(i as f32) * 1.25, 3.0 + i as f32 / 8.0]).collect();
    let faces = vec![vec![0, 1, 2, 3], vec![3, 4, 5, 6, 7], vec![7, 0, 2]];
    (pos, faces)
}

fn expected_fans(faces: &[Vec<u32>]) -> Vec<[u32; 3]> {
    let mut out = Vec::new();
    for f in faces {
        for j in 2..f.len() {
            out.push([f[0], f[j - 1], f[j]]);
        }
    }
    out
}

fn write_ply(format: &str, pos: &[[f32; 3]], faces: &[Vec<u32>]) -> Vec<u8> {
    let mut out = Vec::new();
    write!(
        out,
        "ply\r\nformat {format} 1.0\ncomment extra properties on purpose\nobj_info x\nelement vertex {}\n\
         property uchar red\nproperty double x\nproperty list uchar short tags\nproperty float y\nproperty short q\nproperty float z\nproperty float nx\n\
         element face {}\nproperty int flags\nproperty list uchar uint vertex_indices\nproperty float quality\n\
         element edge 2\nproperty int vertex1\nproperty int vertex2\nend_header\n",
        pos.len(),
        faces.len()
    )
    .unwrap();
    let le = format == "binary_little_endian";
    macro_rules! put {
        ($v:expr) => {
            if le { out.extend_from_slice(&$v.to_le_bytes()) } else { out.extend_from_slice(&$v.to_be_bytes()) }
        };
    }
    for (i, p) in pos.iter().enumerate() {
        if format == "ascii" {
            writeln!(out, "{} {} 2 7 -9 {} 5 {} 0.5", 200 + i, p[0], p[1], p[2]).unwrap();
        } else {
            out.push(200 + i as u8);
            put!(p[0] as f64);
            out.push(2);
            put!(7i16);
            put!(-9i16);
            put!(p[1]);
            put!(5i16);
            put!(p[2]);
            put!(0.5f32);
        }
    }
    for f in faces {
        if format == "ascii" {
            let idx: Vec<String> = f.iter().map(|i| i.to_string()).collect();
            writeln!(out, "-3 {} {} 0.25", f.len(), idx.join(" ")).unwrap();
        } else {
            put!(-3i32);
            out.push(f.len() as u8);
            for &i in f {
                put!(i);
            }
            put!(0.25f32);
        }
    }
    for e in [[0i32, 1], [1, 2]] {
        if format == "ascii" {
            writeln!(out, "{} {}", e[0], e[1]).unwrap();
        } else {
            put!(e[0]);
            put!(e[1]);
        }
    }
    out
}

#[test]
fn ply_all_encodings_with_extra_properties() {
    let (pos, faces) = poly_fixture();
    for format in ["ascii", "binary_little_endian", "binary_big_endian"] {
        let bytes = write_ply(format, &pos, &faces);
        let m = parse_ply(&bytes).unwrap_or_else(|e| panic!("{format}: {e}"));
        assert_eq!(m.positions, pos, "{format}");
        assert_eq!(m.indices, expected_fans(&faces), "{format}");
        assert_eq!(m.indices.len(), 2 + 3 + 1);
    }
}

#[test]
fn ply_truncated_and_bad_inputs_are_errors() {
    let (pos, faces) = poly_fixture();
    for format in ["ascii", "binary_little_endian", "binary_big_endian"] {
        let bytes = write_ply(format, &pos, &faces);
        let header_end = bytes.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
        for cut in [header_end - 3, header_end + 5, bytes.len() - 30] {
            assert!(parse_ply(&bytes[..cut]).is_err(), "{format} cut at {cut}");
        }
    }
    assert!(parse_ply(b"plx\nformat ascii 1.0\nend_header\n").is_err());
    let oob = b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n3 0 0 1\n";
    assert!(parse_ply(oob).is_err());
}

#[test]
fn obj_corner_forms_and_negative_indices() {
    let src = "# test\nmtllib x.mtl\no thing\nv 0 0 0\nv 1 0 0\nv 1 1 0 1.0\nv 0 1 0\nvt 0 0\nvn 0 0 1\n\
               g a\nusemtl m\nf 1 2 3\nf 1/1 3/1 4/1\nf 1/1/1 2/1/1 3/1/1 4/1/1\nf 2//1 3//1 4//1\n\
               v 2 2 2\nf -1 -2 -3\ns off\nf -5/1/1 -4//1 \\\n -3\n";
    let m = parse_obj(src.as_bytes()).unwrap();
    assert_eq!(m.positions.len(), 5);
    assert_eq!(m.positions[2], [1.0, 1.0, 0.0]);
    assert_eq!(m.positions[4], [2.0, 2.0, 2.0]);
    assert_eq!(
        m.indices,
        vec![[0, 1, 2], [0, 2, 3], [0, 1, 2], [0, 2, 3], [1, 2, 3], [4, 3, 2], [0, 1, 2]]
    );
    assert!(parse_obj(b"v 0 0 0\nf 1 2 3\n").is_err());
    assert!(parse_obj(b"v 0 0 0\nv 1 1 1\nf 1 0 2\n").is_err());
}

#[test]
fn procedural_is_deterministic_and_in_range() {
    let a = random_soup(1000, 7);
    assert_eq!(a, random_soup(1000, 7));
    assert_ne!(a, random_soup(1000, 8));
    assert_eq!(a.indices.len(), 1000);
    assert!(a.positions.iter().flatten().all(|c| (0.0..=1.0).contains(c)));
    // Mean edge length ~ n^-1/2 (1.5 x spread x random offsets): a soup, not points nor slabs.
    let mean_edge: f32 = (0..1000)
        .map(|i| {
            let [p, q, _] = a.triangle(i);
            ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).sqrt()
        })
        .sum::<f32>()
        / 1000.0;
    assert!(mean_edge > 0.01 && mean_edge < 0.2, "{mean_edge}");
    let t = terrain(16);
    assert_eq!(t.positions.len(), 17 * 17);
    assert_eq!(t.indices.len(), 2 * 16 * 16);
    assert!(t.max_index() < 17 * 17);
    // Every upward-facing triangle: (b-a)x(c-a) has positive y.
    for i in 0..t.indices.len() {
        let [p, q, r] = t.triangle(i);
        let (e1, e2) = ([q[0] - p[0], q[2] - p[2]], [r[0] - p[0], r[2] - p[2]]);
        assert!(e1[1] * e2[0] - e1[0] * e2[1] > 0.0);
    }
}

#[test]
fn instance_record_layout() {
    let r = InstanceRecord {
        transform: [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0, 11.0, 12.0],
        custom_index: 0x123456,
        mask: 0xAB,
        sbt_offset: 0x654321,
        flags: 0x0F,
        reference: 0x1122_3344_5566_7788,
    };
    let b = r.to_bytes();
    assert_eq!(&b[0..4], &1.0f32.to_le_bytes());
    assert_eq!(&b[44..48], &12.0f32.to_le_bytes());
    assert_eq!(&b[48..52], &[0x56, 0x34, 0x12, 0xAB]);
    assert_eq!(&b[52..56], &[0x21, 0x43, 0x65, 0x0F]);
    assert_eq!(&b[56..64], &[0x88, 0x77, 0x66, 0x55, 0x44, 0x33, 0x22, 0x11]);
    assert_eq!(InstanceRecord::from_bytes(&b), r);
    let recs = instance_records(10, &[100, 200, 300], 1);
    assert_eq!(recs.len(), 10);
    assert_eq!(recs[4].reference, 200);
    assert_eq!(InstanceRecord::pack(&recs).len(), 640);
    for rec in &recs {
        // Rows of the linear part are orthogonal with equal norms (rotation x uniform scale).
        let row = |k: usize| glam::Vec3::new(rec.transform[4 * k], rec.transform[4 * k + 1], rec.transform[4 * k + 2]);
        let (a, b, c) = (row(0), row(1), row(2));
        assert!(a.dot(b).abs() < 1e-4 && a.dot(c).abs() < 1e-4 && b.dot(c).abs() < 1e-4);
        assert!((a.length() - c.length()).abs() < 1e-4 && a.length() >= 0.5 - 1e-5 && a.length() < 2.0 + 1e-5);
    }
}

#[test]
fn byte_views() {
    let m = Mesh { positions: vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0]], indices: vec![[0, 2, 1]] };
    let v = m.vertex_bytes();
    assert_eq!(v.len(), 36);
    assert_eq!(&v[12..16], &4.0f32.to_le_bytes());
    assert_eq!(m.index_bytes(), [0u32, 2, 1].iter().flat_map(|i| i.to_le_bytes()).collect::<Vec<_>>());
    assert_eq!(m.index_bytes_u16().unwrap(), vec![0, 0, 2, 0, 1, 0]);
    let u = m.unindexed_vertex_bytes();
    assert_eq!(&u[12..16], &7.0f32.to_le_bytes());
    let big = Mesh { positions: vec![[0.0; 3]; 70000], indices: vec![[0, 1, 69999]] };
    assert!(big.index_bytes_u16().is_none());
}

#[test]
fn hostile_bytes_never_panic() {
    let mut rng = Rng::new(99);
    let (pos, faces) = poly_fixture();
    let seeds: Vec<Vec<u8>> = vec![
        write_ply("ascii", &pos, &faces),
        write_ply("binary_little_endian", &pos, &faces),
        write_ply("binary_big_endian", &pos, &faces),
        b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf -1 -2 -3\n".to_vec(),
    ];
    for round in 0..4000 {
        let mut b = seeds[round % seeds.len()].clone();
        for _ in 0..1 + round % 6 {
            let i = rng.below(b.len() as u32) as usize;
            match rng.below(3) {
                0 => b[i] = rng.next_u32() as u8,
                1 => b.truncate(i),
                _ => b.insert(i, b"0123456789 -\n/e."[rng.below(16) as usize]),
            }
            if b.is_empty() {
                break;
            }
        }
        // Any result is fine; a panic or an out-of-range index is not.
        for m in [parse_ply(&b), parse_obj(&b)].into_iter().flatten() {
            let n = m.positions.len() as u32;
            assert!(m.indices.iter().flatten().all(|&i| i < n));
        }
    }
    // A header that declares billions of elements must not allocate them up front.
    let huge = b"ply\nformat binary_little_endian 1.0\nelement vertex 4000000000\nproperty float x\nproperty float y\nproperty float z\nend_header\n\0\0\0\0";
    assert!(parse_ply(huge).is_err());
}
