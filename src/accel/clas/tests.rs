//! Unit tests of the cluster formats: argument-record layouts and bitfields, truncation.
use super::args::*;
use super::*;

#[test]
fn record_layouts_match_the_registry() {
    // Offsets from nv-extensions.md B.4 (gcc offsetof).
    let r = BuildTriangleClusterInfo { index_buffer_stride: 0x1111, vertex_buffer: 0x2222_3333_4444_5555, ..Default::default() };
    let b = bytemuck::bytes_of(&r);
    assert_eq!(&b[16..18], &0x1111u16.to_le_bytes());
    assert_eq!(&b[32..40], &0x2222_3333_4444_5555u64.to_le_bytes());
    let t = BuildTriangleClusterTemplateInfo { instantiation_bounding_box_limit: 7, ..Default::default() };
    assert_eq!(&bytemuck::bytes_of(&t)[64..72], &7u64.to_le_bytes());
    let i = InstantiateClusterInfo { cluster_template_address: 9, vertex_buffer: StridedDeviceAddress { start_address: 10, stride_in_bytes: 11 }, ..Default::default() };
    let ib = bytemuck::bytes_of(&i);
    assert_eq!((&ib[8..16], &ib[16..24], &ib[24..32]), (&9u64.to_le_bytes()[..], &10u64.to_le_bytes()[..], &11u64.to_le_bytes()[..]));
    let l = BuildClustersBottomLevelInfo { cluster_references_count: 1, cluster_references_stride: 2, cluster_references: 3 };
    assert_eq!(bytemuck::bytes_of(&l), &[1, 0, 0, 0, 2, 0, 0, 0, 3, 0, 0, 0, 0, 0, 0, 0]);
}

#[test]
fn bitfields_pack_like_c() {
    // triangleCount:9 vertexCount:9 positionTruncateBitCount:6 indexType:4 opacityMicromapIndexType:4
    let w = pack_counts(511, 256, 63, 4, 2);
    assert_eq!(w, 0x1FF | (256 << 9) | (63 << 18) | (4 << 24) | (2 << 28));
    let r = BuildTriangleClusterInfo { counts: w, ..Default::default() };
    assert_eq!((r.triangle_count(), r.vertex_count(), r.position_truncate_bit_count(), r.index_type(), r.opacity_micromap_index_type()), (511, 256, 63, 4, 2));
    let g = GeometryIndexAndFlags::new(0x12_3456, 5);
    assert_eq!(g.0, 0x12_3456 | 5 << 29);
    assert_eq!((g.geometry_index(), g.geometry_flags(), g.reserved()), (0x12_3456, 5, 0));
    for off in [-8_388_608, -1, 0, 1, 8_388_607] {
        let i = InstantiateClusterInfo { geometry_word: InstantiateClusterInfo::pack_geometry_index_offset(off) | 0xAB << 24, ..Default::default() };
        assert_eq!((i.geometry_index_offset(), i.reserved()), (off, 0xAB));
    }
}

#[test]
fn truncation_clears_low_bits() {
    assert_eq!(truncate(1.0 + f32::EPSILON, 1).to_bits(), 1.0f32.to_bits());
    assert_eq!(truncate(-3.75, 0), -3.75);
    assert_eq!(truncate(-3.75, 32).to_bits(), 0);
    assert_eq!(truncate(f32::from_bits(0x4049_0FDB), 8).to_bits(), 0x4049_0F00);
}

#[test]
fn clas_tree_node_counts_stay_under_the_size_query_bound() {
    for t in 0..=MAX_TRIANGLES as u64 {
        let nodes = super::tree::local_node_count(t);
        assert!(nodes <= t.div_ceil(12) + 1, "{t} triangles: {nodes} nodes");
        assert!(nodes <= super::tree::local_node_bound(1, t));
        let exact = super::format::clas_nodes_offset(t) + 64 * nodes;
        assert_eq!(clas_size(t), exact);
        assert!(clas_size(t) <= HEADER_SIZE + 47 * t + 131, "{t}");
    }
}

/// Every slot of a CLAS tree lies in exactly one leaf, inside every box on its path, and the
/// order is a permutation of the triangles; brute force over the tree for each count.
#[test]
fn clas_trees_cover_every_triangle_once_inside_their_boxes() {
    let mut seed = 0x9E37_79B9_7F4A_7C15u64;
    let mut next = move || {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        (seed >> 40) as f32 / (1u64 << 24) as f32 * 4.0 - 2.0
    };
    for t in [1usize, 3, 4, 5, 16, 17, 63, 64, 65, 128, 200, 256] {
        let tris: Vec<[f32; 9]> = (0..t).map(|_| std::array::from_fn(|_| next())).collect();
        let tree = super::tree::build_local(&tris);
        assert_eq!(tree.nodes.len() as u64, super::tree::local_node_count(t as u64));
        // The bounds are the exact box of every vertex (brute force).
        let flat: Vec<f32> = tris.iter().flatten().copied().collect();
        let want: [f32; 6] = std::array::from_fn(|k| {
            let axis = flat.iter().skip(k % 3).step_by(3);
            if k < 3 { axis.fold(f32::INFINITY, |a, &x| a.min(x)) } else { axis.fold(f32::NEG_INFINITY, |a, &x| a.max(x)) }
        });
        assert_eq!(tree.bounds, want, "{t} triangles");
        let mut order: Vec<u32> = tree.order.iter().map(|&i| i as u32).collect();
        order.sort_unstable();
        assert_eq!(order, (0..t as u32).collect::<Vec<_>>());
        let mut seen = vec![0u32; t];
        // (node, boxes of the path)
        let mut stack = vec![(0u32, Vec::<[f32; 6]>::new())];
        while let Some((n, path)) = stack.pop() {
            let node = tree.nodes[n as usize];
            for c in 0..node.child_count as usize {
                let mut p = path.clone();
                p.push(node.child_box(c));
                match node.kind[c] {
                    crate::accel::layout::CHILD_INTERNAL => {
                        assert!(node.child[c] > n);
                        stack.push((node.child[c], p));
                    }
                    k => {
                        for s in node.child[c]..node.child[c] + k as u32 {
                            seen[s as usize] += 1;
                            let tri = tris[tree.order[s as usize] as usize];
                            for b in &p {
                                for v in tri.chunks_exact(3) {
                                    assert!((0..3).all(|a| b[a] <= v[a] && v[a] <= b[a + 3]), "{t} triangles: slot {s} outside its box");
                                }
                            }
                        }
                    }
                }
            }
        }
        assert!(seen.iter().all(|&k| k == 1), "{t} triangles: {seen:?}");
    }
}
