//! Negative tests of vkCmdBuildClusterAccelerationStructureIndirectNV and
//! vkGetClusterAccelerationStructureBuildSizesNV: one per valid-usage check Arbor implements
//! (docs/CLUSTERS.md lists them). The validation layer is off (it predates the extension and
//! every input is invalid on purpose, in exactly one way); each test checks that
//! 1. the diagnostics channel names the VUID, and no other error is reported;
//! 2. nothing changed outside what may be written: every input, destination, address and size
//!    array lives in a guarded buffer (0xA5) and every buffer is compared with a snapshot. A
//!    command-wide violation writes nothing at all; a per-element one writes element 0's
//!    result, address and size, and nothing of element 1 (the broken one);
//! 3. the process lives and a valid command afterwards, on the same device, builds what the
//!    library builds from the same input.
//!
//! Usage-flag mismatches and the scratch rules are reported and the command runs (Arbor never
//! writes scratch; public clients commit the usage mismatches): those tests check the results.
mod harness;

use std::ffi::c_void;

use arbor::accel::clas::{self, args::*};
use arbor::accel::{MapView, VertexFormat};
use ash::vk;
use harness::accel::{Accel, ALL_USAGE};
use harness::clas::*;
use harness::vuid::{guarded, guarded_data, guarded_with, serial, snapshot, verify, without, Region, FILL};

const CLAS_VUID: &str = "VUID-VkClusterAccelerationStructureBuildTriangleClusterInfoNV-";
const TEMPLATE_VUID: &str = "VUID-VkClusterAccelerationStructureBuildTriangleClusterTemplateInfoNV-";
const INFO_VUID: &str = "VUID-VkClusterAccelerationStructureCommandsInfoNV-";
const CMD_VUID: &str = "VUID-vkCmdBuildClusterAccelerationStructureIndirectNV-";
const INPUT_VUID: &str = "VUID-VkClusterAccelerationStructureTriangleClusterInputNV-";
const RESERVED: &str = "VUID-VkClusterAccelerationStructureGeometryIndexAndGeometryFlagsNV-reserved-10487";

/// What a broken rule does to the command.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Outcome {
    /// Nothing is written.
    Skipped,
    /// Element 0 completes, element 1 (the broken one) writes nothing.
    Element1,
    /// Reported as a warning or a non-enforced error; both elements complete.
    Runs,
}

/// The inputs every case starts from: one 8-triangle cluster (9 vertices, 16-bit indices) in
/// guarded buffers, two CLASes and two templates (with and without vertices) built by the
/// library from it and uploaded, and per-triangle geometry words.
struct Fixture {
    ib: Region,
    vb: Region,
    words: Region,
    view: MapView,
    clas: [u64; 2],
    template_with: u64,
    template_without: u64,
}

fn cluster_record(f: &Fixture, a: &Accel, k: u32) -> BuildTriangleClusterInfo {
    BuildTriangleClusterInfo {
        cluster_id: 10 + k,
        counts: pack_counts(8, 9, 0, 2, 0),
        base_geometry_index_and_geometry_flags: GeometryIndexAndFlags::new(k, 0),
        index_buffer: f.ib.address(a),
        vertex_buffer: f.vb.address(a),
        ..Default::default()
    }
}

fn fixture(a: &Accel) -> Fixture {
    let (v, i) = grid_cluster(2, 0.0, 0.5);
    let vbytes = bytes_of(&v.iter().flatten().copied().collect::<Vec<f32>>());
    let (ib, vb) = (guarded_data(a, &bytes_of(&i)), guarded_data(a, &vbytes));
    let words = guarded_data(a, &bytes_of(&[0u32; 8]));
    let mut view = MapView::new();
    view.insert(ib.address(a), bytes_of(&i));
    view.insert(vb.address(a), vbytes);
    let mut f = Fixture { ib, vb, words, view, clas: [0; 2], template_with: 0, template_without: 0 };
    let upload = |bytes: Vec<u8>| guarded_data(a, &bytes).address(a);
    for k in 0..2 {
        let mut b = vec![0u8; clas::clas_size(8) as usize];
        clas::build_clas(&cluster_record(&f, a, k), VertexFormat::R32G32B32Sfloat, &f.view, &mut b).unwrap();
        f.clas[k as usize] = upload(b);
    }
    for with in [true, false] {
        let r = BuildTriangleClusterInfo { vertex_buffer: if with { f.vb.address(a) } else { 0 }, ..cluster_record(&f, a, 0) };
        let mut b = vec![0u8; clas::template_size(8, with) as usize];
        clas::build_template(&r, VertexFormat::R32G32B32Sfloat, None, &f.view, &mut b).unwrap();
        *(if with { &mut f.template_with } else { &mut f.template_without }) = upload(b);
    }
    f
}

/// One command of two elements: the op inputs, the records, and the command's fields, which a
/// case breaks in one way before it runs.
struct Case {
    op: OpType,
    mode: OpMode,
    max_count: u32,
    flags: u32,
    tri: TriangleInput,
    bl: BottomLevelInput,
    mv: MoveInput,
    records: [Vec<u8>; 2],
    src_stride: u64,
    /// Applied to the command after its regions are placed.
    tweak: Option<Tweak>,
    dst_usage: vk::BufferUsageFlags,
    scratch_usage: vk::BufferUsageFlags,
    src_usage: vk::BufferUsageFlags,
}

/// A change to the command once its regions are placed.
type Tweak = Box<dyn Fn(&mut CommandsInfo, &Regions, &Accel)>;

/// Where a case's command reads and writes.
struct Regions {
    dst: Region,
    addrs: Region,
    sizes: Region,
    scratch: Region,
    src: Region,
    count: Region,
}

fn case(f: &Fixture, a: &Accel, op: OpType, mode: OpMode) -> Case {
    let rec = |k: u32| -> Vec<u8> {
        match op {
            OpType::BuildTriangleCluster => bytemuck::bytes_of(&cluster_record(f, a, k)).to_vec(),
            OpType::BuildTriangleClusterTemplate => bytemuck::bytes_of(&BuildTriangleClusterTemplateInfo { cluster: cluster_record(f, a, k), instantiation_bounding_box_limit: 0 }).to_vec(),
            OpType::InstantiateTriangleCluster => bytemuck::bytes_of(&InstantiateClusterInfo {
                cluster_id_offset: 100 + k,
                geometry_word: 0,
                cluster_template_address: f.template_with,
                vertex_buffer: StridedDeviceAddress { start_address: f.vb.address(a), stride_in_bytes: 12 },
            })
            .to_vec(),
            OpType::BuildClustersBottomLevel => {
                let refs = guarded_data(a, &bytes_of(&f.clas)).address(a);
                bytemuck::bytes_of(&BuildClustersBottomLevelInfo { cluster_references_count: 1 + k, cluster_references_stride: 8, cluster_references: refs }).to_vec()
            }
            OpType::MoveObjects => f.clas[k as usize].to_le_bytes().to_vec(),
            OpType::GetClusterTemplateIndices => f.template_with.to_le_bytes().to_vec(),
        }
    };
    Case {
        op,
        mode,
        max_count: 2,
        flags: 0,
        tri: triangle_input(9, 18, 0),
        bl: bottom_level_input(3, 2),
        mv: move_input(ObjectType::TriangleCluster as i32, 2 * clas::clas_size(8)),
        records: [rec(0), rec(1)],
        src_stride: 0,
        tweak: None,
        dst_usage: ALL_USAGE,
        scratch_usage: ALL_USAGE,
        src_usage: ALL_USAGE,
    }
}

impl Case {
    fn input(&self) -> InputInfo {
        let p: *const c_void = match self.op {
            OpType::BuildClustersBottomLevel => &self.bl as *const BottomLevelInput as *const c_void,
            OpType::MoveObjects => &self.mv as *const MoveInput as *const c_void,
            _ => &self.tri as *const TriangleInput as *const c_void,
        };
        InputInfo { flags: self.flags, ..input(self.op, self.mode, self.max_count, p) }
    }

    fn with(mut self, tweak: impl Fn(&mut CommandsInfo, &Regions) + 'static) -> Case {
        self.tweak = Some(Box::new(move |i, r, _| tweak(i, r)));
        self
    }

    /// Element 1's explicit destination moved to `offset` from the destination region's start.
    fn destination1(mut self, offset: impl Fn(&Regions) -> u64 + 'static) -> Case {
        self.tweak = Some(Box::new(move |_, r, a| r.addrs.write(a, 8, &(r.dst.address(a) + offset(r)).to_le_bytes())));
        self
    }

    /// Element 1's record, changed by `change` as the record type `T`.
    fn record1<T: bytemuck::Pod>(mut self, change: impl FnOnce(&mut T)) -> Case {
        let mut r: T = bytemuck::pod_read_unaligned(&self.records[1]);
        change(&mut r);
        self.records[1] = bytemuck::bytes_of(&r).to_vec();
        self
    }
}

/// A device with the extension (validation off), its helper and the fixture; after `f`, a
/// valid command on the same device must still build what the library builds.
fn scenario(feature_off: bool, f: impl FnOnce(&harness::Context, &Nv, &Accel, &Fixture)) {
    let _serial = serial();
    let mut opts = harness::Options { validation: false, acceleration_structure: true, cluster_feature_off: feature_off, ..Default::default() };
    opts.device_extensions.push(EXT);
    let ctx = harness::Context::new(opts);
    let api = nv(&ctx);
    let a = Accel::new(&ctx);
    let fx = fixture(&a);
    f(&ctx, &api, &a, &fx);
    if !feature_off {
        let c = case(&fx, &a, OpType::BuildTriangleCluster, OpMode::ImplicitDestinations);
        let (regs, _) = run(&ctx, &api, &a, &c);
        assert_results(&a, &fx, &c, &regs, 2);
    }
    a.destroy();
    ctx.finish();
}

// One function: the regions of a command, its fields, and the submission.
/// Places the case's regions, records and submits its command; returns the regions and the
/// snapshot taken just before the submission.
fn run(ctx: &harness::Context, api: &Nv, a: &Accel, c: &Case) -> (Regions, harness::vuid::Snapshot) {
    let inp = c.input();
    let sizes = api.sizes(ctx, &inp);
    let one = api.sizes(ctx, &InputInfo { op_mode: OpMode::ExplicitDestinations as i32, ..inp }).acceleration_structure_size.next_multiple_of(64);
    let dst_len = if c.mode == OpMode::ImplicitDestinations { sizes.acceleration_structure_size } else { 2 * one };
    let stride = if c.src_stride == 0 { c.op.record_size() } else { c.src_stride };
    let mut src_bytes = vec![0u8; (stride + c.op.record_size()) as usize];
    src_bytes[..c.records[0].len()].copy_from_slice(&c.records[0]);
    src_bytes[stride as usize..stride as usize + c.records[1].len()].copy_from_slice(&c.records[1]);
    let regs = Regions {
        dst: guarded_with(a, dst_len.max(64), c.dst_usage),
        addrs: guarded(a, 16),
        sizes: guarded(a, 8),
        scratch: guarded_with(a, sizes.build_scratch_size, c.scratch_usage),
        src: guarded_with(a, src_bytes.len() as u64, c.src_usage),
        count: guarded_data(a, &2u32.to_le_bytes()),
    };
    regs.src.write(a, 0, &src_bytes);
    if c.mode == OpMode::ExplicitDestinations {
        let d = regs.dst.address(a);
        regs.addrs.write(a, 0, &bytes_of(&[d, d + one]));
    }
    let mut info = commands(inp);
    info.dst_implicit_data = if c.mode == OpMode::ImplicitDestinations { regs.dst.address(a) } else { 0 };
    info.scratch_data = regs.scratch.address(a);
    info.dst_addresses_array = region(regs.addrs.address(a), 8, 16);
    info.dst_sizes_array = region(regs.sizes.address(a), 4, 8);
    info.src_infos_array = region(regs.src.address(a), c.src_stride, src_bytes.len() as u64);
    info.src_infos_count = regs.count.address(a);
    if let Some(t) = &c.tweak {
        t(&mut info, &regs, a);
    }
    let snap = snapshot(a);
    // SAFETY: a recording command buffer; the info and its op input outlive the call.
    a.submit(|cb| unsafe { (api.cmd_build)(cb, &info) });
    (regs, snap)
}

/// The library's result for element `k` of a case (what the driver must have written).
fn expected(a: &Accel, f: &Fixture, c: &Case, k: usize) -> Vec<u8> {
    match c.op {
        OpType::BuildTriangleCluster => {
            let r: BuildTriangleClusterInfo = bytemuck::pod_read_unaligned(&c.records[k]);
            let mut b = vec![0u8; clas::clas_size(r.triangle_count() as u64) as usize];
            clas::build_clas(&r, VertexFormat::R32G32B32Sfloat, &f.view, &mut b).unwrap();
            b
        }
        OpType::MoveObjects => {
            let mut b = vec![0u8; clas::clas_size(8) as usize];
            clas::build_clas(&cluster_record(f, a, k as u32), VertexFormat::R32G32B32Sfloat, &f.view, &mut b).unwrap();
            b
        }
        _ => Vec::new(),
    }
}

/// The first `n` elements' results are where their addresses say, with their sizes.
fn assert_results(a: &Accel, f: &Fixture, c: &Case, regs: &Regions, n: usize) {
    let addrs: Vec<u64> = collect(&regs.addrs.read(a));
    let sizes: Vec<u32> = collect(&regs.sizes.read(a));
    for k in 0..n {
        let want = expected(a, f, c, k);
        if want.is_empty() {
            assert!(sizes[k] > 0 && sizes[k] != u32::from_le_bytes([FILL; 4]), "element {k}: a size is written");
            continue;
        }
        assert_eq!(sizes[k] as usize, want.len(), "element {k}: its size");
        let at = addrs[k] - regs.dst.address(a);
        assert_eq!(regs.dst.read(a)[at as usize..at as usize + want.len()], want[..], "element {k}: its result");
    }
}

/// Runs a case that breaks `vuid` and checks 1 and 2 (3 is `scenario`'s).
fn expect(ctx: &harness::Context, api: &Nv, a: &Accel, f: &Fixture, c: Case, vuid: &str, outcome: Outcome) {
    let mark = harness::diagnostics().len();
    let (regs, snap) = run(ctx, api, a, &c);
    let tail = harness::diagnostics()[mark..].to_string();
    // A rule without a VUID is named by a phrase of its message instead.
    let tag = if vuid.starts_with("VUID-") { format!("[{vuid}]") } else { vuid.to_string() };
    let named: Vec<&str> = tail.lines().filter(|l| l.contains(&tag)).collect();
    assert!(!named.is_empty(), "no diagnostic names [{vuid}]; the driver reported:\n{tail}");
    let ours = |l: &&str| ["arbor: error: ", "arbor: warning: "].iter().any(|p| l.starts_with(&format!("{p}{CMD}: ")) || l.starts_with(&format!("{p}vkGetClusterAccelerationStructureBuildSizesNV: ")));
    assert!(named.iter().all(ours), "{tail}");
    assert!(named.iter().any(|l| l.contains(CMD)), "the command names [{vuid}]:\n{tail}");
    for l in tail.lines().filter(|l| l.starts_with("arbor: error:")) {
        assert!(l.contains(&tag), "another error besides [{vuid}]: {l}");
    }
    let slots = |r: &Region, k: u64, w: u64| Region { buf: r.buf, offset: r.offset + k * w, len: w };
    match outcome {
        Outcome::Skipped => verify(a, &snap, &[]),
        Outcome::Element1 => {
            let addrs: Vec<u64> = collect(&regs.addrs.read(a));
            let first = if c.mode == OpMode::ExplicitDestinations { addrs[0] } else { addrs.first().copied().unwrap_or(0) };
            let size = u32::from_le_bytes(regs.sizes.read(a)[..4].try_into().unwrap()) as u64;
            let result = if c.mode == OpMode::ComputeSizes { Region { len: 0, ..regs.dst } } else { Region { buf: regs.dst.buf, offset: regs.dst.offset + first - regs.dst.address(a), len: size } };
            verify(a, &snap, &[result, slots(&regs.addrs, 0, 8), slots(&regs.sizes, 0, 4)]);
            assert_eq!(regs.sizes.read(a)[4..], [FILL; 4], "element 1's size is not written");
            if c.mode != OpMode::ComputeSizes {
                assert_results(a, f, &c, &regs, 1);
            }
        }
        Outcome::Runs => {
            verify(a, &snap, &[regs.dst, regs.addrs, regs.sizes]);
            assert_results(a, f, &c, &regs, 2);
        }
    }
}

/// `vuid_test!(name, op, mode, vuid, outcome, |f, a, case| -> Case)`: one test of one check.
macro_rules! vuid_test {
    ($name:ident, $op:ident, $mode:ident, $vuid:expr, $outcome:ident, $make:expr) => {
        #[test]
        fn $name() {
            scenario(false, |ctx, api, a, f| {
                let make: &dyn Fn(&Fixture, &Accel, Case) -> Case = &$make;
                let c = make(f, a, case(f, a, OpType::$op, OpMode::$mode));
                expect(ctx, api, a, f, c, name($vuid).as_str(), Outcome::$outcome);
            });
        }
    };
}

fn name(s: impl AsRef<str>) -> String {
    s.as_ref().to_string()
}

fn cat(a: &str, b: &str) -> String {
    format!("{a}{b}")
}

// The feature (10443; 10438 for the size query) on a device that chained it off.
#[test]
fn feature_not_enabled() {
    scenario(true, |ctx, api, a, f| {
        let c = case(f, a, OpType::BuildTriangleCluster, OpMode::ImplicitDestinations);
        let mark = harness::diagnostics().len();
        let _ = api.sizes(ctx, &c.input());
        assert!(harness::diagnostics()[mark..].contains("[VUID-vkGetClusterAccelerationStructureBuildSizesNV-clusterAccelerationStructure-10438]"));
        let mark = harness::diagnostics().len();
        let (_, snap) = run(ctx, api, a, &c);
        verify(a, &snap, &[]);
        let tail = harness::diagnostics()[mark..].to_string();
        assert!(tail.contains(&format!("[{CMD_VUID}clusterAccelerationStructure-10443]")) && tail.contains("command skipped"), "{tail}");
    });
}

// The op input (10439-10442), in the size query and the command.
fn input_case(make: impl Fn(&mut TriangleInput), vuid: &str) {
    scenario(false, |ctx, api, a, f| {
        let mut c = case(f, a, OpType::BuildTriangleCluster, OpMode::ImplicitDestinations);
        make(&mut c.tri);
        let mark = harness::diagnostics().len();
        let _ = api.sizes(ctx, &c.input());
        let tail = harness::diagnostics()[mark..].to_string();
        assert!(tail.contains(&format!("vkGetClusterAccelerationStructureBuildSizesNV: [{vuid}]")), "{tail}");
        // The command is recorded with a valid input's sizes (the query's answer for this one
        // may be smaller), and must skip.
        expect(ctx, api, a, f, c, vuid, Outcome::Skipped);
    });
}

#[test]
fn vertex_format_without_acceleration_structure_support() {
    input_case(|t| t.vertex_format = vk::Format::R8G8B8A8_UINT.as_raw(), &cat(INPUT_VUID, "vertexFormat-10439"));
}
#[test]
fn input_max_cluster_triangle_count_over_the_limit() {
    input_case(|t| t.max_cluster_triangle_count = 257, &cat(INPUT_VUID, "maxClusterTriangleCount-10440"));
}
#[test]
fn input_max_cluster_vertex_count_over_the_limit() {
    input_case(|t| t.max_cluster_vertex_count = 257, &cat(INPUT_VUID, "maxClusterVertexCount-10441"));
}
#[test]
fn input_min_truncate_over_32() {
    input_case(|t| t.min_position_truncate_bit_count = 33, &cat(INPUT_VUID, "minPositionTruncateBitCount-10442"));
}

// Command-wide rules on the command's fields: the command is skipped.
vuid_test!(dst_addresses_stride_below_8, BuildTriangleCluster, ImplicitDestinations, cat(INFO_VUID, "dstAddressesArray-10474"), Skipped, |_, _, c| c.with(|i, _| i.dst_addresses_array.stride = 4));
vuid_test!(dst_sizes_stride_below_4, BuildTriangleCluster, ImplicitDestinations, cat(INFO_VUID, "dstSizesArray-10475"), Skipped, |_, _, c| c.with(|i, _| i.dst_sizes_array.stride = 2));
vuid_test!(src_infos_stride_below_the_record, BuildTriangleCluster, ImplicitDestinations, cat(INFO_VUID, "srcInfosArray-10476"), Skipped, |_, _, c| c.with(|i, _| i.src_infos_array.stride = 32));
vuid_test!(implicit_without_dst_implicit_data, BuildTriangleCluster, ImplicitDestinations, cat(INFO_VUID, "opMode-12309"), Skipped, |_, _, c| c.with(|i, _| i.dst_implicit_data = 0));
vuid_test!(compute_sizes_without_dst_sizes, BuildTriangleCluster, ComputeSizes, cat(INFO_VUID, "opMode-12312"), Skipped, |_, _, c| c.with(|i, _| i.dst_sizes_array.device_address = 0));
vuid_test!(explicit_without_dst_addresses, BuildTriangleCluster, ExplicitDestinations, cat(INFO_VUID, "opMode-12313"), Skipped, |_, _, c| c.with(|i, _| i.dst_addresses_array.device_address = 0));
vuid_test!(implicit_data_too_small, BuildTriangleCluster, ImplicitDestinations, cat(INFO_VUID, "opMode-12310"), Skipped, |_, _, c| c.with(|i, r| i.dst_implicit_data += r.dst.len.next_multiple_of(256) + harness::vuid::GUARD - 64));
vuid_test!(implicit_clas_misaligned, BuildTriangleCluster, ImplicitDestinations, cat(INFO_VUID, "input-12317"), Skipped, |_, _, c| c.with(|i, _| i.dst_implicit_data += 4));
vuid_test!(implicit_template_misaligned, BuildTriangleClusterTemplate, ImplicitDestinations, cat(INFO_VUID, "input-12318"), Skipped, |_, _, c| c.with(|i, _| i.dst_implicit_data += 8));
vuid_test!(implicit_instantiation_misaligned, InstantiateTriangleCluster, ImplicitDestinations, cat(INFO_VUID, "input-12319"), Skipped, |_, _, c| c.with(|i, _| i.dst_implicit_data += 4));
vuid_test!(implicit_data_overlaps_scratch, BuildTriangleCluster, ImplicitDestinations, cat(CMD_VUID, "dstImplicitData-10456"), Skipped, |_, _, c| c.with(|i, _| i.scratch_data = i.dst_implicit_data + 64));
vuid_test!(src_infos_count_misaligned, BuildTriangleCluster, ImplicitDestinations, cat(INFO_VUID, "srcInfosCount-12322"), Skipped, |_, _, c| c.with(|i, _| i.src_infos_count += 2));
vuid_test!(move_implicit_data_below_the_moved_bytes, MoveObjects, ImplicitDestinations, cat(INFO_VUID, "opMode-12311"), Skipped, |_, _, c| c.with(|i, r| i.dst_implicit_data += r.dst.len.next_multiple_of(256) + harness::vuid::GUARD - 256));

// The element count and the array it indexes.
vuid_test!(count_above_max_acceleration_structure_count, BuildTriangleCluster, ImplicitDestinations, cat(CMD_VUID, "pCommandInfos-10453"), Element1, |_, _, mut c| {
    c.max_count = 1;
    c
});
vuid_test!(src_infos_size_below_the_count, BuildTriangleCluster, ImplicitDestinations, cat(CMD_VUID, "pCommandInfos-10454"), Element1, |_, _, c| c.with(|i, _| i.src_infos_array.size = 64));

// Reported, not enforced: scratch and usage flags (both elements complete).
vuid_test!(scratch_misaligned, BuildTriangleCluster, ImplicitDestinations, cat(CMD_VUID, "scratchData-10447"), Runs, |_, _, c| c.with(|i, _| i.scratch_data += 4));
vuid_test!(scratch_too_small, BuildTriangleCluster, ImplicitDestinations, cat(CMD_VUID, "scratchData-10446"), Runs, |_, _, c| c.with(|i, r| i.scratch_data += r.scratch.len + harness::vuid::GUARD - 128));
vuid_test!(scratch_zero, BuildTriangleCluster, ImplicitDestinations, cat(INFO_VUID, "buildScratchSize-12321"), Runs, |_, _, c| c.with(|i, _| i.scratch_data = 0));
vuid_test!(scratch_without_storage_buffer_usage, BuildTriangleCluster, ImplicitDestinations, cat(CMD_VUID, "pCommandInfos-10457"), Runs, |_, _, mut c| {
    c.scratch_usage = without(vk::BufferUsageFlags::STORAGE_BUFFER);
    c
});
vuid_test!(src_infos_without_build_input_usage, BuildTriangleCluster, ImplicitDestinations, cat(CMD_VUID, "pCommandInfos-10458"), Runs, |_, _, mut c| {
    c.src_usage = without(vk::BufferUsageFlags::ACCELERATION_STRUCTURE_BUILD_INPUT_READ_ONLY_KHR);
    c
});
vuid_test!(implicit_data_without_storage_usage, BuildTriangleCluster, ImplicitDestinations, cat(CMD_VUID, "pCommandInfos-10459"), Runs, |_, _, mut c| {
    c.dst_usage = without(vk::BufferUsageFlags::ACCELERATION_STRUCTURE_STORAGE_KHR);
    c
});

// Explicit destinations: the element is skipped.
vuid_test!(explicit_clas_misaligned, BuildTriangleCluster, ExplicitDestinations, cat(INFO_VUID, "input-12317"), Element1, |_, _, c| c.destination1(|_| 512 + 8));
vuid_test!(explicit_template_misaligned, BuildTriangleClusterTemplate, ExplicitDestinations, cat(INFO_VUID, "input-12318"), Element1, |_, _, c| c.destination1(|_| 1024 + 8));
vuid_test!(explicit_instantiation_misaligned, InstantiateTriangleCluster, ExplicitDestinations, cat(INFO_VUID, "input-12319"), Element1, |_, _, c| c.destination1(|_| 512 + 8));
vuid_test!(explicit_blas_misaligned, BuildClustersBottomLevel, ExplicitDestinations, cat(INFO_VUID, "opMode-12316"), Element1, |_, _, c| c.destination1(|r| r.dst.len / 2 + 16));
vuid_test!(explicit_destination_too_small, BuildTriangleCluster, ExplicitDestinations, cat(INFO_VUID, "opMode-12314"), Element1, |_, _, c| c.destination1(|r| r.dst.len.next_multiple_of(256) + harness::vuid::GUARD - 64));
vuid_test!(explicit_destinations_overlap, BuildTriangleCluster, ExplicitDestinations, cat(INFO_VUID, "opMode-12315"), Element1, |_, _, c| c.destination1(|_| 64));
vuid_test!(explicit_destination_overlaps_scratch, BuildTriangleCluster, ExplicitDestinations, cat(CMD_VUID, "dstAddressesArray-10455"), Element1, |_, _, mut c| {
    c.tweak = Some(Box::new(|_, r, a| r.addrs.write(a, 8, &r.scratch.address(a).to_le_bytes())));
    c
});

// The rules of one CLAS record (element 1 broken, element 0 built).
fn clas1(c: Case, change: impl FnOnce(&mut BuildTriangleClusterInfo)) -> Case {
    c.record1(change)
}
fn tpl1(c: Case, change: impl FnOnce(&mut BuildTriangleClusterInfo)) -> Case {
    c.record1(|r: &mut BuildTriangleClusterTemplateInfo| change(&mut r.cluster))
}
fn counts(r: &mut BuildTriangleClusterInfo, t: u32, v: u32, bits: u32, it: u32, omm: u32) {
    r.counts = pack_counts(t, v, bits, it, omm);
}

vuid_test!(clas_cluster_id_all_ones, BuildTriangleCluster, ImplicitDestinations, cat(CLAS_VUID, "clusterID-10488"), Element1, |_, _, c| clas1(c, |r| r.cluster_id = u32::MAX));
vuid_test!(clas_triangle_count_over_the_limit, BuildTriangleCluster, ImplicitDestinations, cat(CLAS_VUID, "triangleCount-10489"), Element1, |_, _, c| clas1(c, |r| counts(r, 300, 9, 0, 2, 0)));
vuid_test!(clas_vertex_count_over_the_limit, BuildTriangleCluster, ImplicitDestinations, cat(CLAS_VUID, "vertexCount-10490"), Element1, |_, _, c| clas1(c, |r| counts(r, 8, 300, 0, 2, 0)));
vuid_test!(clas_index_type_not_one_bit, BuildTriangleCluster, ImplicitDestinations, cat(CLAS_VUID, "indexType-10491"), Element1, |_, _, c| clas1(c, |r| counts(r, 8, 9, 0, 3, 0)));
vuid_test!(clas_omm_index_type_not_one_bit, BuildTriangleCluster, ImplicitDestinations, cat(CLAS_VUID, "opacityMicromapIndexType-10492"), Element1, |_, _, mut c| {
    c.flags = arbor::accel::clas::check::ALLOW_CLUSTER_OPACITY_MICROMAPS;
    clas1(c, |r| {
        counts(r, 8, 9, 0, 2, 6);
        r.opacity_micromap_array = 0x1000;
    })
});
vuid_test!(clas_truncation_below_the_input_minimum, BuildTriangleCluster, ImplicitDestinations, cat(CLAS_VUID, "positionTruncateBitCount-10493"), Element1, |_, _, mut c| {
    c.tri.min_position_truncate_bit_count = 0;
    clas1(c, |r| counts(r, 8, 9, 33, 2, 0))
});
vuid_test!(clas_index_stride_not_a_multiple, BuildTriangleCluster, ImplicitDestinations, cat(CLAS_VUID, "indexBufferStride-10494"), Element1, |_, _, c| clas1(c, |r| r.index_buffer_stride = 3));
vuid_test!(clas_vertex_stride_not_a_multiple, BuildTriangleCluster, ImplicitDestinations, cat(CLAS_VUID, "vertexBufferStride-10495"), Element1, |_, _, c| clas1(c, |r| r.vertex_buffer_stride = 14));
vuid_test!(clas_geometry_index_over_the_limit, BuildTriangleCluster, ImplicitDestinations, cat(CLAS_VUID, "baseGeometryIndex-10496"), Element1, |f, a, c| {
    f.words.write(a, 0, &bytes_of(&[1u32; 8]));
    let words = f.words.address(a);
    clas1(c, move |r| {
        r.base_geometry_index_and_geometry_flags = GeometryIndexAndFlags::new((1 << 24) - 2, 0);
        r.geometry_index_and_flags_buffer = words;
    })
});
vuid_test!(clas_opacity_micromap_without_the_flag, BuildTriangleCluster, ImplicitDestinations, cat(CLAS_VUID, "opacityMicromapArray-10881"), Element1, |_, _, c| clas1(c, |r| r.opacity_micromap_array = 0x1000));
vuid_test!(clas_base_geometry_word_reserved_bits, BuildTriangleCluster, ImplicitDestinations, RESERVED, Element1, |_, _, c| clas1(c, |r| r.base_geometry_index_and_geometry_flags = GeometryIndexAndFlags(1 << 25)));
vuid_test!(clas_triangle_geometry_word_reserved_bits, BuildTriangleCluster, ImplicitDestinations, RESERVED, Element1, |f, a, c| {
    f.words.write(a, 12, &(1u32 << 26).to_le_bytes());
    let words = f.words.address(a);
    clas1(c, move |r| r.geometry_index_and_flags_buffer = words)
});
vuid_test!(clas_triangles_over_the_input_bound, BuildTriangleCluster, ImplicitDestinations, "exceeds the input's maxClusterTriangleCount", Element1, |_, _, mut c| {
    c.tri.max_cluster_triangle_count = 8;
    clas1(c, |r| counts(r, 9, 9, 0, 2, 0))
});
vuid_test!(clas_total_triangles_over_the_input_bound, BuildTriangleCluster, ImplicitDestinations, "against the input's maxTotalTriangleCount", Element1, |_, _, mut c| {
    c.tri.max_total_triangle_count = 12;
    c
});

// The same rules as a template names them, and its own (10505).
vuid_test!(template_cluster_id_all_ones, BuildTriangleClusterTemplate, ImplicitDestinations, cat(TEMPLATE_VUID, "clusterID-10497"), Element1, |_, _, c| tpl1(c, |r| r.cluster_id = u32::MAX));
vuid_test!(template_triangle_count_over_the_limit, BuildTriangleClusterTemplate, ImplicitDestinations, cat(TEMPLATE_VUID, "triangleCount-10498"), Element1, |_, _, c| tpl1(c, |r| counts(r, 300, 9, 0, 2, 0)));
vuid_test!(template_vertex_count_over_the_limit, BuildTriangleClusterTemplate, ImplicitDestinations, cat(TEMPLATE_VUID, "vertexCount-10499"), Element1, |_, _, c| tpl1(c, |r| counts(r, 8, 300, 0, 2, 0)));
vuid_test!(template_index_type_not_one_bit, BuildTriangleClusterTemplate, ImplicitDestinations, cat(TEMPLATE_VUID, "indexType-10500"), Element1, |_, _, c| tpl1(c, |r| counts(r, 8, 9, 0, 0, 0)));
vuid_test!(template_omm_index_type_not_one_bit, BuildTriangleClusterTemplate, ImplicitDestinations, cat(TEMPLATE_VUID, "opacityMicromapIndexType-10501"), Element1, |_, _, mut c| {
    c.flags = arbor::accel::clas::check::ALLOW_CLUSTER_OPACITY_MICROMAPS;
    tpl1(c, |r| {
        counts(r, 8, 9, 0, 2, 0);
        r.opacity_micromap_array = 0x1000;
    })
});
vuid_test!(template_truncation_over_32, BuildTriangleClusterTemplate, ImplicitDestinations, cat(TEMPLATE_VUID, "positionTruncateBitCount-10502"), Element1, |_, _, c| tpl1(c, |r| counts(r, 8, 9, 40, 2, 0)));
vuid_test!(template_index_stride_not_a_multiple, BuildTriangleClusterTemplate, ImplicitDestinations, cat(TEMPLATE_VUID, "indexBufferStride-10503"), Element1, |_, _, c| tpl1(c, |r| r.index_buffer_stride = 5));
vuid_test!(template_vertex_stride_not_a_multiple, BuildTriangleClusterTemplate, ImplicitDestinations, cat(TEMPLATE_VUID, "vertexBufferStride-10504"), Element1, |_, _, c| tpl1(c, |r| r.vertex_buffer_stride = 13));
vuid_test!(template_bounds_misaligned, BuildTriangleClusterTemplate, ImplicitDestinations, cat(TEMPLATE_VUID, "instantiationBoundingBoxLimit-10505"), Element1, |f, a, c| {
    let at = f.words.address(a) + 4;
    c.record1(move |r: &mut BuildTriangleClusterTemplateInfo| r.instantiation_bounding_box_limit = at)
});
vuid_test!(template_geometry_index_over_the_limit, BuildTriangleClusterTemplate, ImplicitDestinations, cat(TEMPLATE_VUID, "baseGeometryIndex-10506"), Element1, |_, _, c| tpl1(c, |r| r.base_geometry_index_and_geometry_flags = GeometryIndexAndFlags::new((1 << 24) - 1, 0)));
vuid_test!(template_opacity_micromap_without_the_flag, BuildTriangleClusterTemplate, ImplicitDestinations, cat(TEMPLATE_VUID, "opacityMicromapArray-10882"), Element1, |_, _, c| tpl1(c, |r| r.opacity_micromap_array = 0x1000));

// Instantiation against its template.
const INSTANTIATE_VUID: &str = "VUID-VkClusterAccelerationStructureInstantiateClusterInfoNV-";
vuid_test!(instantiation_without_vertices_from_a_template_without, InstantiateTriangleCluster, ImplicitDestinations, cat(INSTANTIATE_VUID, "vertexBuffer-10507"), Element1, |f, _, c| {
    let t = f.template_without;
    c.record1(move |r: &mut InstantiateClusterInfo| {
        r.cluster_template_address = t;
        r.vertex_buffer.start_address = 0;
    })
});
vuid_test!(instantiation_with_another_vertex_format, InstantiateTriangleCluster, ImplicitDestinations, cat(INSTANTIATE_VUID, "vertexBuffer-10508"), Element1, |_, _, mut c| {
    // Element 0 reads the template's own vertices: the format is only compared when new ones come.
    c.tri.vertex_format = vk::Format::R32G32_SFLOAT.as_raw();
    let r0: InstantiateClusterInfo = bytemuck::pod_read_unaligned(&c.records[0]);
    c.records[0] = bytemuck::bytes_of(&InstantiateClusterInfo { vertex_buffer: StridedDeviceAddress::default(), ..r0 }).to_vec();
    c
});
vuid_test!(instantiation_reserved_bits, InstantiateTriangleCluster, ImplicitDestinations, cat(INSTANTIATE_VUID, "reserved-10509"), Element1, |_, _, c| c.record1(|r: &mut InstantiateClusterInfo| r.geometry_word = 1 << 28));
vuid_test!(instantiation_geometry_offset_out_of_range, InstantiateTriangleCluster, ImplicitDestinations, cat(INSTANTIATE_VUID, "geometryIndexOffset-10510"), Element1, |_, _, c| {
    c.record1(|r: &mut InstantiateClusterInfo| r.geometry_word = InstantiateClusterInfo::pack_geometry_index_offset(-1))
});

// Cluster BLAS records.
const BLAS_VUID: &str = "VUID-VkClusterAccelerationStructureBuildClustersBottomLevelInfoNV-";
vuid_test!(blas_duplicate_references, BuildClustersBottomLevel, ImplicitDestinations, cat(BLAS_VUID, "clusterReferences-10484"), Element1, |f, a, c| {
    let refs = guarded_data(a, &bytes_of(&[f.clas[0], f.clas[0]])).address(a);
    c.record1(move |r: &mut BuildClustersBottomLevelInfo| r.cluster_references = refs)
});
vuid_test!(blas_references_short_of_the_count, BuildClustersBottomLevel, ImplicitDestinations, cat(BLAS_VUID, "clusterReferences-10485"), Element1, |f, a, c| {
    // The references end where their buffer ends.
    let r = harness::vuid::guarded(a, 8);
    let end = a.buf(r.buf).address + a.buf(r.buf).size - 8;
    a.buf(r.buf).write((a.buf(r.buf).size - 8) as usize, &f.clas[0].to_le_bytes());
    c.record1(move |x: &mut BuildClustersBottomLevelInfo| x.cluster_references = end)
});
vuid_test!(blas_reference_stride_below_8, BuildClustersBottomLevel, ImplicitDestinations, cat(BLAS_VUID, "clusterReferencesStride-10486"), Element1, |_, _, c| c.record1(|r: &mut BuildClustersBottomLevelInfo| r.cluster_references_stride = 4));
vuid_test!(blas_references_over_the_per_structure_bound, BuildClustersBottomLevel, ImplicitDestinations, cat(INFO_VUID, "input-12323"), Element1, |_, _, mut c| {
    c.bl.max_cluster_count_per_acceleration_structure = 1;
    c
});
vuid_test!(blas_references_over_the_total_bound, BuildClustersBottomLevel, ImplicitDestinations, cat(INFO_VUID, "input-12323"), Element1, |_, _, mut c| {
    c.bl.max_total_cluster_count = 2;
    c
});

// Moves and template indices.
vuid_test!(move_of_another_object_type, MoveObjects, ImplicitDestinations, "VUID-VkClusterAccelerationStructureMoveObjectsInfoNV-srcAccelerationStructure-10483", Element1, |f, _, mut c| {
    c.records[1] = f.template_with.to_le_bytes().to_vec();
    c
});
vuid_test!(move_over_max_moved_bytes, MoveObjects, ImplicitDestinations, cat(INFO_VUID, "input-10469"), Element1, |_, _, mut c| {
    c.mv.max_moved_bytes = clas::clas_size(8) + 16;
    c
});
vuid_test!(template_indices_of_a_clas, GetClusterTemplateIndices, ImplicitDestinations, "VUID-VkClusterAccelerationStructureGetTemplateIndicesInfoNV-clusterTemplateAddress-10833", Element1, |f, _, mut c| {
    c.records[1] = f.clas[0].to_le_bytes().to_vec();
    c
});
