//! Negative tests of vkCmdBuildPartitionedAccelerationStructuresNV: one per valid-usage check
//! Arbor makes, host-side at record time and on device-memory data at execution
//! (docs/PTLAS.md lists which is where). Each scenario first builds a valid PTLAS into a
//! guarded destination, then records one build that is invalid in exactly one way and checks
//! that
//! 1. the diagnostics channel names the VUID (`arbor: error: <command>: [VUID-...] ...`) and
//!    reports no other error;
//! 2. nothing changed but the PTLAS header of the destination (every buffer of the test, guard
//!    bytes around destination, scratch and inputs included, is compared with a snapshot), and
//!    that header marks the destination invalid;
//! 3. the process lives and a valid build on the same device afterwards traverses the grid.
//!
//! The validation layer is off: every input is invalid on purpose (and the layer here predates
//! the extension). Usage-flag mismatches that real clients commit are reported as warnings and
//! the build runs (`usage_mismatches_are_reported_and_the_build_runs`).
mod harness;

use std::ffi::c_void;

use arbor::accel::{self, MapView};
use ash::vk;
use harness::ptlas::*;
use harness::vuid::*;

const PTLAS_CMD: &str = "vkCmdBuildPartitionedAccelerationStructuresNV";
const HEADER: u64 = 128;

/// VkPartitionedAccelerationStructureWriteInstanceDataNV (104 bytes).
#[derive(Clone, Copy)]
struct Write {
    transform: [f32; 12],
    aabb: [f32; 6],
    id: u32,
    mask: u32,
    sbt: u32,
    flags: u32,
    index: u32,
    partition: u32,
    blas: u64,
}

impl Write {
    fn bytes(&self) -> Vec<u8> {
        let mut b: Vec<u8> = self.transform.iter().chain(&self.aabb).flat_map(|x| x.to_le_bytes()).collect();
        for w in [self.id, self.mask, self.sbt, self.flags, self.index, self.partition] {
            b.extend(w.to_le_bytes());
        }
        b.extend(self.blas.to_le_bytes());
        b
    }
}

/// VkPartitionedAccelerationStructureUpdateInstanceDataNV (16 bytes).
fn update(index: u32, sbt: u32, blas: u64) -> Vec<u8> {
    [index.to_le_bytes().as_slice(), &sbt.to_le_bytes(), &blas.to_le_bytes()].concat()
}

/// VkPartitionedAccelerationStructureWritePartitionTranslationDataNV (16 bytes).
fn translation(partition: u32, t: [f32; 3]) -> Vec<u8> {
    [partition.to_le_bytes(), t[0].to_le_bytes(), t[1].to_le_bytes(), t[2].to_le_bytes()].concat()
}

/// The device of every scenario: the grid BLAS, the PTLAS sizes for `input(8, 8, 2, 8)`, a
/// guarded destination holding a valid PTLAS, scratch and the count word.
struct Fx<'c> {
    a: Accel<'c>,
    sizes_fn: PfnSizes,
    build_fn: PfnBuild,
    blas: u64,
    view: MapView,
    size: u64,
    dst: Region,
    scratch: Region,
    count: Region,
}

impl Fx<'_> {
    /// Instance 0 (identity, partition 0) over the grid, instance 1 under it (global).
    fn writes(&self) -> [Write; 2] {
        let w = Write { transform: IDENTITY, aabb: [0.0; 6], id: 5, mask: 0xFF, sbt: 0, flags: 0, index: 0, partition: 0, blas: self.blas };
        let mut below = IDENTITY;
        below[11] = -5.0;
        [w, Write { transform: below, index: 1, partition: GLOBAL, ..w }]
    }
    fn data(&self, records: &[Vec<u8>]) -> Region {
        guarded_data(&self.a, &records.concat())
    }
    /// An srcInfos array of `(op, argData records)` elements, packed strides.
    fn ops(&self, elements: &[(u32, Vec<Vec<u8>>)]) -> Region {
        let recs: Vec<Vec<u8>> = elements.iter().map(|(op, r)| op_record(*op, r.len() as u32, if r.is_empty() { 0 } else { self.data(r).address(&self.a) }, 0)).collect();
        self.data(&recs)
    }
    fn valid_ops(&self) -> Region {
        self.ops(&[(0, self.writes().iter().map(Write::bytes).collect())])
    }
    fn set_count(&self, n: u32) {
        self.count.write(&self.a, 0, &n.to_le_bytes());
    }
    fn info(&self, ops: &Region, dst: u64) -> BuildInfo {
        let s = |r: &Region| r.address(&self.a);
        build_info(input(8, 8, 2, 8), 0, dst, s(&self.scratch), s(ops), s(&self.count))
    }
    fn record(&self, info: &BuildInfo) {
        // SAFETY: a valid command buffer; the info's pointers live through the call.
        self.a.submit(|cb| unsafe { (self.build_fn)(cb, info) });
    }
    fn sizes(&self, inp: &InstancesInput) -> vk::AccelerationStructureBuildSizesInfoKHR<'static> {
        let mut sizes = vk::AccelerationStructureBuildSizesInfoKHR::default();
        // SAFETY: valid input and output structs.
        unsafe { (self.sizes_fn)(self.a.ctx.device.handle(), inp, &mut sizes) };
        sizes
    }
    /// A valid from-scratch build of `writes()` into `dst`, which then traverses like the grid.
    fn valid_build(&self, dst: &Region) {
        let ops = self.valid_ops();
        self.set_count(1);
        let mark = harness::diagnostics().len();
        self.record(&self.info(&ops, dst.address(&self.a)));
        assert_grid_hits(&dst.read(&self.a), &self.view);
        let said = harness::diagnostics()[mark..].to_string();
        assert!(!said.contains(PTLAS_CMD), "the valid build was reported: {said}");
    }
    /// `len` bytes at offset GUARD of a buffer that ends with them (guard bytes before only).
    fn tight(&self, len: u64) -> Region {
        let b = self.a.buffer(GUARD + len);
        self.a.fill(b, FILL);
        Region { buf: b, offset: GUARD, len }
    }
    fn header(r: &Region) -> Region {
        Region { len: HEADER, ..*r }
    }
    fn ptlas_valid(&self, r: &Region) -> bool {
        accel::header(&r.read(&self.a)).is_some()
    }
}

fn context_with_extension() -> harness::Context {
    let mut exts = harness::default_device_extensions();
    exts.push(EXT);
    let opts = harness::Options { validation: false, acceleration_structure: true, device_extensions: exts, ..Default::default() };
    harness::Context::new(opts)
}

/// A device with the extension, the fixture with a valid PTLAS in `dst`; after `f`, a valid
/// build into a fresh destination must traverse and every guard of the fixture hold.
fn scenario(f: impl FnOnce(&Fx)) {
    let _serial = serial();
    let ctx = context_with_extension();
    let a = Accel::new(&ctx);
    let Nv { sizes: sizes_fn, build: build_fn } = functions(&ctx);
    let m = upload_grid(&a);
    let (blas, _) = valid_blas(&a, &m, NO_FLAGS);
    let blas_address = a.address_of(blas.s);
    let mut view = MapView::new();
    view.insert(blas_address, blas.r.read(&a));
    let (dst, scratch, count) = (guarded(&a, 1), guarded(&a, 1), guarded(&a, 4));
    let mut fx = Fx { a, sizes_fn, build_fn, blas: blas_address, view, size: 0, dst, scratch, count };
    let sizes = fx.sizes(&input(8, 8, 2, 8));
    assert!(sizes.acceleration_structure_size >= HEADER && sizes.build_scratch_size > 0);
    fx.size = sizes.acceleration_structure_size;
    (fx.dst, fx.scratch) = (guarded(&fx.a, fx.size), guarded(&fx.a, sizes.build_scratch_size));
    fx.valid_build(&fx.dst);
    f(&fx);
    let fresh = guarded(&fx.a, fx.size);
    fx.valid_build(&fresh);
    for r in [fx.dst, fx.scratch, fx.count, fresh] {
        assert_guards(&fx.a, r);
    }
    fx.a.destroy();
    ctx.finish();
}

/// Run `submit` and check 1-2 of the module comment: an error line naming `vuid` (any error
/// line containing `needle` where no numbered VUID names the rule) and no other error; no byte
/// changed outside `writable`; `invalidated` held a valid PTLAS before and none after.
fn expect(fx: &Fx, vuid: Option<&str>, needle: &str, writable: &[Region], invalidated: Option<&Region>, submit: impl FnOnce()) {
    if let Some(d) = invalidated {
        assert!(fx.ptlas_valid(d), "test setup: the destination should hold a valid PTLAS before");
    }
    let snap = snapshot(&fx.a);
    let mark = harness::diagnostics().len();
    submit();
    let tail = harness::diagnostics()[mark..].to_string();
    let want = match vuid {
        Some(v) => format!("arbor: error: {PTLAS_CMD}: [{v}] "),
        None => format!("arbor: error: {PTLAS_CMD}: "),
    };
    assert!(tail.lines().any(|l| l.starts_with(&want) && l.contains(needle)), "expected a line starting {want:?} containing {needle:?}; the driver reported:\n{tail}");
    for l in tail.lines() {
        assert!(!l.contains("panic") && !l.contains("internal error"), "the driver hit an internal error: {l}");
        if l.starts_with("arbor: error:") {
            assert!(l.starts_with(&want), "unexpected diagnostic besides {want:?}: {l}");
        }
    }
    verify(&fx.a, &snap, writable);
    if let Some(d) = invalidated {
        assert!(!fx.ptlas_valid(d), "the destination of the skipped build still reads as a valid PTLAS");
    }
}

fn cmd_vuid_nv(n: u32) -> String {
    format!("VUID-{PTLAS_CMD}-pBuildInfo-{n}")
}

/// A from-scratch build into the fixture's destination, whose op records (`ops`, `count`
/// elements) break a rule: reported by `vuid`, skipped, the destination marked invalid.
fn expect_records_refused(fx: &Fx, vuid: &str, needle: &str, ops: Region, count: u32, inp: InstancesInput) {
    fx.set_count(count);
    let info = BuildInfo { input: inp, ..fx.info(&ops, fx.dst.address(&fx.a)) };
    expect(fx, Some(vuid), needle, &[Fx::header(&fx.dst)], Some(&fx.dst), || fx.record(&info));
}

/// The fixture's valid writes plus `bad`, in one WRITE_INSTANCE element.
fn expect_write_refused(vuid: &str, needle: &str, bad: impl FnOnce(&Fx) -> Write) {
    scenario(|fx| {
        let mut records: Vec<Vec<u8>> = fx.writes().iter().map(Write::bytes).collect();
        records.push(bad(fx).bytes());
        let ops = fx.ops(&[(0, records)]);
        expect_records_refused(fx, vuid, needle, ops, 1, input(8, 8, 2, 8));
    });
}

const WRITE_VUID: &str = "VUID-VkPartitionedAccelerationStructureWriteInstanceDataNV-";

#[test]
fn write_instance_index_past_instance_count_10568() {
    expect_write_refused(&format!("{WRITE_VUID}instanceIndex-10568"), "record 2: instanceIndex 8", |fx| Write { index: 8, ..fx.writes()[0] });
}

#[test]
fn write_partition_index_past_partition_count_10569() {
    expect_write_refused(&format!("{WRITE_VUID}partitionIndex-10569"), "partitionIndex 2", |fx| Write { index: 2, partition: 2, ..fx.writes()[0] });
}

#[test]
fn write_mask_above_8_bits_10566() {
    expect_write_refused(&format!("{WRITE_VUID}instanceMask-10566"), "0x1ff", |fx| Write { index: 2, mask: 0x1FF, ..fx.writes()[0] });
}

#[test]
fn write_sbt_offset_above_24_bits_10567() {
    expect_write_refused(&format!("{WRITE_VUID}instanceContributionToHitGroupIndex-10567"), "0x1000000", |fx| Write { index: 2, sbt: 1 << 24, ..fx.writes()[0] });
}

#[test]
fn write_undefined_instance_flags() {
    expect_write_refused(&format!("{WRITE_VUID}instanceFlags-parameter"), "0x40", |fx| Write { index: 2, flags: 0x40, ..fx.writes()[0] });
}

#[test]
fn write_explicit_aabb_inverted_10570() {
    let aabb = [0.0, 0.0, 0.0, -1.0, 1.0, 1.0];
    expect_write_refused(&format!("{WRITE_VUID}explicitAABB-10570"), "not a valid box", |fx| Write { index: 2, flags: 0x10, aabb, ..fx.writes()[0] });
}

#[test]
fn write_same_instance_twice_10565() {
    let vuid = "VUID-VkBuildPartitionedAccelerationStructureIndirectCommandNV-argData-10565";
    expect_write_refused(vuid, "WRITE_INSTANCE record 2: instanceIndex 1", |fx| fx.writes()[1]);
}

fn expect_update_refused(vuid: &str, needle: &str, updates: Vec<Vec<u8>>) {
    scenario(|fx| {
        let ops = fx.ops(&[(1, updates)]);
        expect_records_refused(fx, vuid, needle, ops, 1, input(8, 8, 2, 8));
    });
}

#[test]
fn update_instance_index_past_instance_count_10573() {
    expect_update_refused("VUID-VkPartitionedAccelerationStructureUpdateInstanceDataNV-instanceIndex-10573", "instanceIndex 9", vec![update(0, 1, 0), update(9, 1, 0)]);
}

#[test]
fn update_sbt_offset_above_24_bits_10571() {
    let vuid = "VUID-VkPartitionedAccelerationStructureUpdateInstanceDataNV-instanceContributionToHitGroupIndex-10571";
    expect_update_refused(vuid, "UPDATE_INSTANCE record 0", vec![update(0, 1 << 31, 0)]);
}

#[test]
fn update_same_instance_twice_10565() {
    let vuid = "VUID-VkBuildPartitionedAccelerationStructureIndirectCommandNV-argData-10565";
    expect_update_refused(vuid, "UPDATE_INSTANCE record 2: instanceIndex 0", vec![update(0, 1, 0), update(1, 1, 0), update(0, 2, 0)]);
}

#[test]
fn translation_without_enable_partition_translation_10575() {
    scenario(|fx| {
        let ops = fx.ops(&[(2, vec![translation(0, [1.0, 0.0, 0.0])])]);
        let vuid = "VUID-VkPartitionedAccelerationStructureWritePartitionTranslationDataNV-enablePartitionTranslation-10575";
        expect_records_refused(fx, vuid, "lacks enablePartitionTranslation", ops, 1, input(8, 8, 2, 8));
    });
}

#[test]
fn translation_partition_index_past_partition_count_10574() {
    scenario(|fx| {
        let flags = translation_enabled();
        let inp = InstancesInput { p_next: &flags as *const _ as *const c_void, ..input(8, 8, 2, 8) };
        let ops = fx.ops(&[(2, vec![translation(GLOBAL, [0.0; 3]), translation(2, [1.0, 0.0, 0.0])])]);
        let vuid = "VUID-VkPartitionedAccelerationStructureWritePartitionTranslationDataNV-partitionIndex-10574";
        expect_records_refused(fx, vuid, "record 1: partitionIndex 2", ops, 1, inp);
    });
}

#[test]
fn op_type_repeated_10564() {
    scenario(|fx| {
        let ops = fx.ops(&[(0, vec![]), (1, vec![]), (0, vec![])]);
        expect_records_refused(fx, "VUID-VkBuildPartitionedAccelerationStructureInfoNV-srcInfos-10564", "srcInfos[2].opType 0 is unknown or repeats", ops, 3, input(8, 8, 2, 8));
    });
}

#[test]
fn more_elements_than_op_types_10564() {
    scenario(|fx| {
        let ops = fx.ops(&[(0, vec![]), (1, vec![]), (2, vec![]), (0, vec![])]);
        expect_records_refused(fx, "VUID-VkBuildPartitionedAccelerationStructureInfoNV-srcInfos-10564", "srcInfosCount is 4", ops, 4, input(8, 8, 2, 8));
    });
}

#[test]
fn unknown_op_type() {
    scenario(|fx| {
        let ops = fx.ops(&[(3, vec![])]);
        expect_records_refused(fx, "VUID-VkBuildPartitionedAccelerationStructureIndirectCommandNV-opType-parameter", "opType 3 is unknown", ops, 1, input(8, 8, 2, 8));
    });
}

#[test]
fn src_infos_shorter_than_its_count_10546() {
    scenario(|fx| {
        // One element at the very end of its buffer, two counted.
        let b = fx.a.buffer(GUARD + 24);
        fx.a.fill(b, FILL);
        let ops = Region { buf: b, offset: GUARD, len: 24 };
        ops.write(&fx.a, 0, &op_record(1, 0, 0, 0));
        expect_records_refused(fx, &cmd_vuid_nv(10546), "the srcInfos array of 2 elements", ops, 2, input(8, 8, 2, 8));
    });
}

#[test]
fn src_infos_count_unresolvable() {
    scenario(|fx| {
        let mut info = fx.info(&fx.valid_ops(), fx.dst.address(&fx.a));
        info.src_infos_count = freed_address(&fx.a, 256);
        let vuid = "VUID-VkBuildPartitionedAccelerationStructureInfoNV-srcInfosCount-parameter";
        expect(fx, Some(vuid), "srcInfosCount word", &[Fx::header(&fx.dst)], Some(&fx.dst), || fx.record(&info));
    });
}

#[test]
fn arg_data_unresolvable() {
    scenario(|fx| {
        let ops = fx.data(&[op_record(0, 1, freed_address(&fx.a, 256), 104)]);
        fx.set_count(1);
        let info = fx.info(&ops, fx.dst.address(&fx.a));
        // No numbered VUID names an argData address that is not device memory.
        expect(fx, None, "srcInfos[0].argData", &[Fx::header(&fx.dst)], Some(&fx.dst), || fx.record(&info));
    });
}

/// The fixture's valid build with `change` applied to its info; refused at record time or at
/// execution with `vuid`; `invalidated`: whether the fixture's destination is marked invalid.
fn expect_info_refused(vuid: &str, needle: &str, invalidated: bool, change: impl FnOnce(&Fx, &mut BuildInfo)) {
    scenario(|fx| {
        fx.set_count(1);
        let mut info = fx.info(&fx.valid_ops(), fx.dst.address(&fx.a));
        change(fx, &mut info);
        let (writable, inv) = if invalidated { (vec![Fx::header(&fx.dst)], Some(&fx.dst)) } else { (vec![], None) };
        expect(fx, Some(vuid), needle, &writable, inv, || fx.record(&info));
        if !invalidated {
            assert!(fx.ptlas_valid(&fx.dst), "a build with another destination invalidated the fixture's");
        }
    });
}

#[test]
fn dst_null_10561() {
    expect_info_refused("VUID-VkBuildPartitionedAccelerationStructureInfoNV-dstAccelerationStructureData-10561", "NULL", false, |_, i| i.dst = 0);
}

#[test]
fn scratch_null_10558() {
    expect_info_refused("VUID-VkBuildPartitionedAccelerationStructureInfoNV-scratchData-10558", "NULL", true, |_, i| i.scratch = 0);
}

#[test]
fn scratch_misaligned_10542() {
    expect_info_refused(&cmd_vuid_nv(10542), "scratchData", true, |_, i| i.scratch += 64);
}

#[test]
fn src_misaligned_10544() {
    expect_info_refused(&cmd_vuid_nv(10544), "srcAccelerationStructureData", true, |_, i| i.src = i.dst + 64);
}

#[test]
fn dst_misaligned_10545() {
    expect_info_refused(&cmd_vuid_nv(10545), "dstAccelerationStructureData", false, |_, i| i.dst += 64);
}

#[test]
fn src_infos_count_misaligned_10563() {
    expect_info_refused("VUID-VkBuildPartitionedAccelerationStructureInfoNV-srcInfosCount-10563", "not aligned to 4", true, |_, i| i.src_infos_count += 2);
}

#[test]
fn partition_count_past_max_partition_count_10535() {
    let vuid = "VUID-VkPartitionedAccelerationStructureInstancesInputNV-partitionCount-10535";
    expect_info_refused(vuid, "exceeds maxPartitionCount", true, |_, i| i.input.partition_count = (1 << 24) - 8);
}

#[test]
fn src_not_a_ptlas_10560() {
    let vuid = "VUID-VkBuildPartitionedAccelerationStructureInfoNV-srcAccelerationStructureData-10560";
    expect_info_refused(vuid, "holds no valid partitioned", true, |fx, i| i.src = guarded(&fx.a, fx.size).address(&fx.a));
}

#[test]
fn in_place_on_memory_that_holds_no_ptlas_10560() {
    let vuid = "VUID-VkBuildPartitionedAccelerationStructureInfoNV-srcAccelerationStructureData-10560";
    expect_info_refused(vuid, "an in-place build", false, |fx, i| {
        i.dst = guarded(&fx.a, fx.size).address(&fx.a);
        i.src = i.dst;
    });
}

#[test]
fn dst_smaller_than_the_queried_size_10543() {
    expect_info_refused(&cmd_vuid_nv(10543), "the build needs", false, |fx, i| i.dst = fx.tight(fx.size - 256).address(&fx.a));
}

#[test]
fn scratch_smaller_than_the_queried_size_10541() {
    expect_info_refused(&cmd_vuid_nv(10541), "scratchData does not hold", true, |fx, i| i.scratch = fx.tight(16).address(&fx.a));
}

#[test]
fn src_overlaps_scratch_10547() {
    expect_info_refused(&cmd_vuid_nv(10547), "overlaps scratch", true, |fx, i| {
        let src = guarded(&fx.a, fx.size);
        fx.valid_build(&src);
        i.src = src.address(&fx.a);
        i.scratch = i.src + 256;
    });
}

#[test]
fn dst_overlaps_scratch_10548() {
    expect_info_refused(&cmd_vuid_nv(10548), "overlaps scratch", true, |_, i| i.scratch = i.dst + 256);
}

#[test]
fn src_overlaps_dst_10549() {
    // The destination starts inside the source: the source must stay intact (nothing writable).
    expect_info_refused(&cmd_vuid_nv(10549), "overlap", false, |fx, i| {
        let src = guarded(&fx.a, fx.size);
        fx.valid_build(&src);
        i.src = src.address(&fx.a);
        i.dst = i.src + 256;
    });
}

/// An in-place build of the structure in a destination sized exactly for `input(8, 8, 2, 8)`
/// with one count raised past what it was sized for (10537–10540).
fn expect_count_past_sized(n: u32, field: &str, raise: impl FnOnce(&mut InstancesInput)) {
    scenario(|fx| {
        let dst = fx.tight(fx.size);
        fx.valid_build(&dst);
        fx.set_count(1);
        let mut info = fx.info(&fx.valid_ops(), dst.address(&fx.a));
        info.src = info.dst;
        raise(&mut info.input);
        expect(fx, Some(&cmd_vuid_nv(n)), &format!("input.{field}"), &[Fx::header(&dst)], Some(&dst), || fx.record(&info));
    });
}

#[test]
fn instance_count_past_the_sized_count_10537() {
    expect_count_past_sized(10537, "instanceCount", |i| i.instance_count = 64);
}

#[test]
fn instances_per_partition_past_the_sized_count_10538() {
    expect_count_past_sized(10538, "maxInstancePerPartitionCount", |i| i.max_instance_per_partition_count = 64);
}

#[test]
fn partition_count_past_the_sized_count_10539() {
    expect_count_past_sized(10539, "partitionCount", |i| i.partition_count = 64);
}

#[test]
fn global_instances_past_the_sized_count_10540() {
    expect_count_past_sized(10540, "maxInstanceInGlobalPartitionCount", |i| i.max_instance_in_global_partition_count = 64);
}

/// A partition holding more instances than maxInstancePerPartitionCount: found by the build
/// itself (membership depends on the state), which clears the destination it had begun.
#[test]
fn partition_over_capacity_fails_the_build() {
    scenario(|fx| {
        let [w0, _] = fx.writes();
        let ops = fx.ops(&[(0, vec![w0.bytes(), Write { index: 1, ..w0 }.bytes()])]);
        fx.set_count(1);
        let info = BuildInfo { input: input(8, 1, 2, 8), ..fx.info(&ops, fx.dst.address(&fx.a)) };
        expect(fx, None, "would hold more than maxInstancePerPartitionCount", &[fx.dst, fx.scratch], Some(&fx.dst), || fx.record(&info));
    });
}

/// Inputs without BUILD_INPUT_READ_ONLY (10551), scratch without STORAGE_BUFFER (10550), a
/// destination without ACCELERATION_STRUCTURE_STORAGE (10552): real clients do this
/// (nv-usage.md); each is a warning naming its VUID, and the build runs.
#[test]
fn usage_mismatches_are_reported_and_the_build_runs() {
    scenario(|fx| {
        let a = &fx.a;
        let bare = |len: u64, flag: vk::BufferUsageFlags| guarded_with(a, len, without(flag));
        let input_flag = vk::BufferUsageFlags::ACCELERATION_STRUCTURE_BUILD_INPUT_READ_ONLY_KHR;
        let records = bare(208, input_flag);
        records.write(a, 0, &fx.writes().iter().flat_map(Write::bytes).collect::<Vec<u8>>());
        let ops = bare(24, input_flag);
        ops.write(a, 0, &op_record(0, 2, records.address(a), 104));
        let count = bare(4, input_flag);
        count.write(a, 0, &1u32.to_le_bytes());
        let scratch = bare(64, vk::BufferUsageFlags::STORAGE_BUFFER);
        let dst = bare(fx.size, vk::BufferUsageFlags::ACCELERATION_STRUCTURE_STORAGE_KHR);
        let info = BuildInfo { scratch: scratch.address(a), src_infos_count: count.address(a), ..fx.info(&ops, dst.address(a)) };
        let mark = harness::diagnostics().len();
        fx.record(&info);
        let said = harness::diagnostics()[mark..].to_string();
        for n in [10550, 10551, 10552] {
            let want = format!("arbor: warning: {PTLAS_CMD}: [{}] ", cmd_vuid_nv(n));
            assert!(said.lines().any(|l| l.starts_with(&want)), "no warning {want:?}; the driver reported:\n{said}");
        }
        assert!(!said.contains("arbor: error:"), "a usage mismatch was rejected: {said}");
        assert_grid_hits(&dst.read(a), &fx.view);
    });
}

/// A write and an update of the same instance in one build: valid Vulkan usage (each array
/// names it once), which NVAPI forbids: a warning, and the write applies before the update.
#[test]
fn write_and_update_of_one_instance_is_a_warning() {
    scenario(|fx| {
        let ops = fx.ops(&[(0, fx.writes().iter().map(Write::bytes).collect()), (1, vec![update(1, 3, fx.blas)])]);
        fx.set_count(2);
        let mark = harness::diagnostics().len();
        fx.record(&fx.info(&ops, fx.dst.address(&fx.a)));
        let said = harness::diagnostics()[mark..].to_string();
        assert!(said.contains("arbor: warning: vkCmdBuildPartitionedAccelerationStructuresNV: 1 instance(s) (first 1) both written and updated"), "{said}");
        assert!(!said.contains("arbor: error:"), "{said}");
        assert_grid_hits(&fx.dst.read(&fx.a), &fx.view);
    });
}

/// VUID 10536 (the feature enabled) cannot be broken through the loader: without the extension
/// enabled at vkCreateDevice, the device does not resolve the command at all.
#[test]
fn without_the_extension_the_command_does_not_resolve_10536() {
    let _serial = serial();
    let ctx = harness::Context::new(harness::Options { validation: false, acceleration_structure: true, ..Default::default() });
    // SAFETY: a live device; a name lookup only.
    let f = unsafe { ctx.instance.get_device_proc_addr(ctx.device.handle(), c"vkCmdBuildPartitionedAccelerationStructuresNV".as_ptr()) };
    assert!(f.is_none(), "the command resolves on a device without the extension");
    ctx.finish();
}
