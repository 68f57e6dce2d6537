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
