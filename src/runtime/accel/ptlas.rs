//! vkCmdBuildPartitionedAccelerationStructuresNV as the queue runs it: the op count and the op
//! records are read from device memory when the command executes (so records written earlier
//! in the same submission, by a shader or vkCmdUpdateBuffer, are seen), checked, and handed to
//! `accel::ptlas::build` with the source, destination and scratch regions.
//!
//! Owns: the device-memory side of a PTLAS build and its valid-usage checks. Must not touch:
//! the blob's bytes (the library's) or raw application pointers (the dispatch layer's).
use ash::vk;

use super::inputs::{DeviceInputs, InputError, InputMemory};
use crate::accel::ptlas::{self, IndirectCommand, Ops, Source, Strided, UpdateInstance, WriteInstance, WriteTranslation};
use crate::diag;
use crate::memory::region::{Region, WriteSet};
use crate::runtime::command::{Exec, ExecContext, ExecError};
use crate::runtime::in_use::Collector;

pub use crate::accel::ptlas::{BuildSizes, Input as PtlasInput};

const CMD: &str = "vkCmdBuildPartitionedAccelerationStructuresNV";
const EXTENSION: &str = "VK_NV_partitioned_acceleration_structure";
/// Alignment of src, dst and scratch (VUIDs 10542, 10544, 10545).
pub const PTLAS_ALIGNMENT: u64 = 256;

fn vuid_name(n: u32) -> String {
    format!("VUID-vkCmdBuildPartitionedAccelerationStructuresNV-pBuildInfo-{n}")
}

/// A lowered VkBuildPartitionedAccelerationStructureInfoNV (addresses only).
#[derive(Clone, Copy, Debug)]
pub struct PtlasBuild {
    pub input: PtlasInput,
    pub src: u64,
    pub dst: u64,
    pub scratch: u64,
    pub src_infos: u64,
    pub src_infos_count: u64,
}

/// vkGetPartitionedAccelerationStructuresBuildSizesNV.
pub fn build_sizes(input: &PtlasInput) -> BuildSizes {
    ptlas::build_sizes(input)
}

/// The largest `partitionCount + maxInstanceInGlobalPartitionCount` (the spec's minimum for
/// maxPartitionCount, 2^24 − 1).
pub const MAX_PARTITION_COUNT: u32 = (1 << 24) - 1;

/// The rules the recorded parameters alone decide, checked when the command is recorded:
/// Some((VUID, message)) for the first one broken.
pub fn record_check(b: &PtlasBuild) -> Option<(String, String)> {
    if b.dst == 0 {
        return Some(("VUID-VkBuildPartitionedAccelerationStructureInfoNV-dstAccelerationStructureData-10561".into(), "dstAccelerationStructureData is NULL".into()));
    }
    // The scratch size is never 0, so scratchData may never be NULL.
    if b.scratch == 0 {
        return Some(("VUID-VkBuildPartitionedAccelerationStructureInfoNV-scratchData-10558".into(), "scratchData is NULL (the queried buildScratchSize is not 0)".into()));
    }
    for (address, n, what) in [(b.scratch, 10542, "scratchData"), (b.src, 10544, "srcAccelerationStructureData"), (b.dst, 10545, "dstAccelerationStructureData")] {
        if !address.is_multiple_of(PTLAS_ALIGNMENT) {
            return Some((vuid_name(n), format!("{what} {address:#x} is not aligned to 256 bytes")));
        }
    }
    if !b.src_infos_count.is_multiple_of(4) {
        return Some(("VUID-VkBuildPartitionedAccelerationStructureInfoNV-srcInfosCount-10563".into(), format!("srcInfosCount {:#x} is not aligned to 4 bytes", b.src_infos_count)));
    }
    let i = &b.input;
    if i.partition_count as u64 + i.max_instance_in_global_partition_count as u64 > MAX_PARTITION_COUNT as u64 {
        let what = format!("partitionCount {} + maxInstanceInGlobalPartitionCount {} exceeds maxPartitionCount {MAX_PARTITION_COUNT}", i.partition_count, i.max_instance_in_global_partition_count);
        return Some(("VUID-VkPartitionedAccelerationStructureInstancesInputNV-partitionCount-10535".into(), what));
    }
    None
}

/// The recorded command. `rejected`: a rule `record_check` decides was broken (and reported
/// when recorded); the build is skipped when the queue reaches it.
pub struct PtlasCommand {
    pub build: PtlasBuild,
    pub rejected: bool,
}

impl Exec for PtlasCommand {
    fn name(&self) -> &'static str {
        CMD
    }
    fn execute(&self, ctx: &ExecContext<'_>) -> Result<(), ExecError> {
        let inputs = DeviceInputs::new(ctx.memory(), CMD);
        let ok = if self.rejected {
            false
        } else if !ctx.device.extension_enabled(EXTENSION) {
            diag::vuid("VUID-vkCmdBuildPartitionedAccelerationStructuresNV-partitionedAccelerationStructure-10536", CMD, "VK_NV_partitioned_acceleration_structure is not enabled; build skipped");
            false
        } else {
            crate::threads::run_parallel(false, || execute(&inputs, &self.build))
        };
        if !ok {
            invalidate(&inputs, &self.build);
            if diag::strict() {
                return Err(ExecError::Invalid { vuid: "strict", message: "a partitioned acceleration-structure build broke a valid-usage rule (ARBOR_STRICT)".into() });
            }
        }
        Ok(())
    }
    fn uses(&self, c: &mut Collector<'_>) {
        let b = &self.build;
        for a in [b.src, b.dst, b.scratch, b.src_infos, b.src_infos_count] {
            c.address(a);
        }
    }
}

/// A skipped build marks its destination invalid: the header of a PTLAS at dst is cleared (a
/// destination that holds none is left as it is, so nothing but a PTLAS header is written).
fn invalidate(mem: &DeviceInputs<'_>, b: &PtlasBuild) {
    let len = ptlas::HEADER_SIZE as u64;
    if b.dst == 0 || mem.view.bytes(b.dst, len).and_then(ptlas::header).is_none() {
        return;
    }
    if let Ok(r) = Region::of_device(mem.space, b.dst, len) {
        r.write_with(ptlas::mark_invalid);
    }
}

/// A usage-flag mismatch real clients commit (nv-usage.md): reported as a warning, never a
/// reason to skip.
fn usage_note(mem: &DeviceInputs<'_>, address: u64, usage: vk::BufferUsageFlags, vuid: u32, what: &str) {
    if address == 0 {
        return;
    }
    if let Err(Ok(found)) = mem.space.resolve_with_usage(address, 1, usage) {
        diag::report(diag::Level::Warn, CMD, &format!("[{}] {what} lies in a buffer without {usage:?} (has {found:?}); used anyway", vuid_name(vuid)));
    }
}

/// Device bytes an input lives in: a usage mismatch is reported (real clients commit it) and
/// the bytes are read anyway; an unresolvable range is reported (with `vuid` where one names
/// it) and gives None.
fn read_input<'m>(mem: &'m DeviceInputs<'_>, address: u64, len: u64, what: &str, vuid: Option<&str>) -> Option<&'m [u8]> {
    match mem.input(address, len, vk::BufferUsageFlags::ACCELERATION_STRUCTURE_BUILD_INPUT_READ_ONLY_KHR) {
        Ok(b) => Some(b),
        Err(InputError::Usage(u)) => {
            diag::report(diag::Level::Warn, CMD, &format!("[{}] {what} lies in a buffer without ACCELERATION_STRUCTURE_BUILD_INPUT_READ_ONLY_BIT_KHR (has {u:?})", vuid_name(10551)));
            mem.view.bytes(address, len)
        }
        Err(e) => {
            let message = format!("{what} at {address:#x} ({len} bytes) does not resolve: {e}; build skipped");
            match vuid {
                Some(v) => diag::vuid(v, CMD, &message),
                None => diag::report(diag::Level::Error, CMD, &message),
            }
            None
        }
    }
}

const OP_TYPE_VUID: &str = "VUID-VkBuildPartitionedAccelerationStructureIndirectCommandNV-opType-parameter";
const UNIQUE_OP_VUID: &str = "VUID-VkBuildPartitionedAccelerationStructureInfoNV-srcInfos-10564";

/// The op records of one build: the count, then each command's strided records.
fn read_ops<'m>(mem: &'m DeviceInputs<'_>, b: &PtlasBuild) -> Option<Ops<'m>> {
    let word = read_input(mem, b.src_infos_count, 4, "the srcInfosCount word", Some("VUID-VkBuildPartitionedAccelerationStructureInfoNV-srcInfosCount-parameter"))?;
    let count = u32::from_le_bytes(word.try_into().ok()?);
    let mut ops = Ops::default();
    if count == 0 {
        return Some(ops);
    }
    if count > 3 {
        diag::vuid(UNIQUE_OP_VUID, CMD, &format!("srcInfosCount is {count}: more elements than op types, so some opType repeats; build skipped"));
        return None;
    }
    let size = std::mem::size_of::<IndirectCommand>() as u64;
    let infos = read_input(mem, b.src_infos, size * count as u64, &format!("the srcInfos array of {count} elements"), Some(&vuid_name(10546)))?;
    let mut seen = [false; 3];
    for k in 0..count {
        let cmd: IndirectCommand = Strided { data: infos, count, stride: size }.get(k)?;
        let op = cmd.op_type as usize;
        if op > 2 || seen[op] {
            let (vuid, why) = if op > 2 { (OP_TYPE_VUID, "not a VkPartitionedAccelerationStructureOpTypeNV") } else { (UNIQUE_OP_VUID, "each element must have a distinct opType") };
            diag::vuid(vuid, CMD, &format!("srcInfos[{k}].opType {} is unknown or repeats an earlier element's ({why}); build skipped", cmd.op_type));
            return None;
        }
        seen[op] = true;
        // Only the low 32 bits of the stride are meaningful (VkStridedDeviceAddressNV).
        let stride = cmd.stride_in_bytes & 0xffff_ffff;
        let span = match op {
            0 => Strided::span::<WriteInstance>(cmd.arg_count, stride),
            1 => Strided::span::<UpdateInstance>(cmd.arg_count, stride),
            _ => Strided::span::<WriteTranslation>(cmd.arg_count, stride),
        };
        let data = if span == 0 { &[][..] } else { read_input(mem, cmd.start_address, span, &format!("srcInfos[{k}].argData"), None)? };
        let s = Strided { data, count: cmd.arg_count, stride };
        match op {
            0 => ops.writes = s,
            1 => ops.updates = s,
            _ => ops.translations = s,
        }
    }
    Some(ops)
}

/// The records' own rules (`accel::ptlas::check_ops`), before anything is written.
fn check_records(input: &PtlasInput, ops: &Ops) -> bool {
    match ptlas::check_ops(input, ops) {
        Ok(notes) => {
            if let Some(i) = notes.written_and_updated.first() {
                let n = notes.written_and_updated.len();
                let msg = format!("{n} instance(s) (first {i}) both written and updated by this build: valid Vulkan usage (the write applies first), but one write or update per instance per build is what the driver feature allows elsewhere (NVAPI)");
                diag::report(diag::Level::Warn, CMD, &msg);
            }
            true
        }
        Err(v) => {
            let message = format!("{}; build skipped", v.message);
            match v.vuid {
                Some(vuid) => diag::vuid(vuid, CMD, &message),
                None => diag::report(diag::Level::Error, CMD, &message),
            }
            false
        }
    }
}

fn overlaps(a: u64, alen: u64, b: u64, blen: u64) -> bool {
    a < b.saturating_add(blen) && b < a.saturating_add(alen)
}

/// A source blob's bytes and its used size.
type SourceBytes<'m> = Option<(&'m [u8], u64)>;

/// The count fields of the input against the capacities a source blob was laid out for:
/// the first that exceeds them, with its VUID (10537–10540: each count must not exceed what
/// the memory was sized for).
fn over_capacity(input: &PtlasInput, h: &ptlas::PtlasHeader) -> Option<(u32, &'static str, u32, u32)> {
    [
        (10537, "instanceCount", input.instance_count, h.instance_capacity),
        (10538, "maxInstancePerPartitionCount", input.max_instance_per_partition_count, h.partition_capacity),
        (10539, "partitionCount", input.partition_count, h.partition_count),
        (10540, "maxInstanceInGlobalPartitionCount", input.max_instance_in_global_partition_count, h.global_capacity),
    ]
    .into_iter()
    .find(|&(_, _, got, cap)| got > cap)
}

/// The source's bytes (with its used size) when it is another blob, and how many bytes of dst
/// the build may use: up to the layout of a grown source, at least `needed`. None: reported.
fn source_and_destination<'m>(mem: &'m DeviceInputs<'_>, b: &PtlasBuild, needed: u64) -> Option<(SourceBytes<'m>, u64)> {
    let header_at = |address: u64| mem.view.bytes(address, ptlas::HEADER_SIZE as u64).and_then(ptlas::header);
    let prior = if b.src == 0 { None } else { header_at(b.src) };
    if b.src != 0 && prior.is_none() {
        let which = if b.src == b.dst { "srcAccelerationStructureData (== dst, an in-place build)" } else { "srcAccelerationStructureData" };
        diag::vuid(SOURCE_VUID, CMD, &format!("{which} {:#x} holds no valid partitioned acceleration structure; build skipped", b.src));
        return None;
    }
    let src = if b.src == 0 || b.src == b.dst {
        None
    } else {
        let used = prior.map(|h| h.used_size).unwrap_or(0);
        match mem.view.bytes(b.src, used) {
            Some(s) => Some((s, used)),
            None => {
                diag::vuid(SOURCE_VUID, CMD, &format!("srcAccelerationStructureData {:#x}: its {used} bytes do not resolve; build skipped", b.src));
                return None;
            }
        }
    };
    // dst may be laid out for a grown source's capacities: give it what its buffer holds, up to that.
    let mut want = needed;
    if let Some(h) = prior {
        let grown = ptlas::Input {
            instance_count: h.instance_capacity.max(b.input.instance_count),
            max_instance_per_partition_count: h.partition_capacity.max(b.input.max_instance_per_partition_count),
            partition_count: h.partition_count.max(b.input.partition_count),
            max_instance_in_global_partition_count: h.global_capacity.max(b.input.max_instance_in_global_partition_count),
            ..b.input
        };
        want = want.max(ptlas::build_sizes(&grown).acceleration_structure_size);
    }
    let room = mem.space.resolve(b.dst, 1).map(|r| r.buffer.size - r.offset).unwrap_or(0);
    if room < needed {
        if let Some((n, field, got, cap)) = prior.as_ref().and_then(|h| over_capacity(&b.input, h)) {
            let what = format!("input.{field} {got} exceeds the {cap} the source structure was sized for, and dst ({room} bytes) cannot hold the larger layout ({needed} bytes); build skipped");
            diag::vuid(&vuid_name(n), CMD, &what);
        } else {
            diag::vuid(&vuid_name(10543), CMD, &format!("dstAccelerationStructureData has {room} bytes; the build needs {needed}; build skipped"));
        }
        return None;
    }
    Some((src, want.min(room)))
}

const SOURCE_VUID: &str = "VUID-VkBuildPartitionedAccelerationStructureInfoNV-srcAccelerationStructureData-10560";

/// Checks, then runs one build. Returns false when anything was invalid (reported once).
fn execute(mem: &DeviceInputs<'_>, b: &PtlasBuild) -> bool {
    usage_note(mem, b.scratch, vk::BufferUsageFlags::STORAGE_BUFFER, 10550, "scratchData");
    usage_note(mem, b.src, vk::BufferUsageFlags::ACCELERATION_STRUCTURE_STORAGE_KHR, 10552, "srcAccelerationStructureData");
    usage_note(mem, b.dst, vk::BufferUsageFlags::ACCELERATION_STRUCTURE_STORAGE_KHR, 10552, "dstAccelerationStructureData");
    let Some(ops) = read_ops(mem, b) else { return false };
    if !check_records(&b.input, &ops) {
        return false;
    }
    let sizes = ptlas::build_sizes(&b.input);
    let Some((src, dst_len)) = source_and_destination(mem, b, sizes.acceleration_structure_size) else { return false };
    if let Some((_, used)) = src {
        if overlaps(b.src, used, b.dst, dst_len) {
            diag::vuid(&vuid_name(10549), CMD, "the source and destination structures overlap; build skipped");
            return false;
        }
        if overlaps(b.src, used, b.scratch, sizes.build_scratch_size) {
            diag::vuid(&vuid_name(10547), CMD, "the source structure overlaps scratch; build skipped");
            return false;
        }
    }
    let dst = match Region::of_device(mem.space, b.dst, dst_len) {
        Ok(r) => r,
        Err(e) => {
            diag::vuid("VUID-VkBuildPartitionedAccelerationStructureInfoNV-dstAccelerationStructureData-parameter", CMD, &format!("dstAccelerationStructureData does not resolve ({e}); build skipped"));
            return false;
        }
    };
    let scratch = match mem.writable(b.scratch, sizes.build_scratch_size) {
        Ok(r) => r,
        Err(e) => {
            diag::vuid(&vuid_name(10541), CMD, &format!("scratchData does not hold {} bytes ({e}); build skipped", sizes.build_scratch_size));
            return false;
        }
    };
    let mut writes = WriteSet::new();
    let Ok(mut claim) = writes.claim([dst, scratch]) else {
        diag::vuid(&vuid_name(10548), CMD, "the destination structure overlaps scratch; build skipped");
        return false;
    };
    let [dst, scratch] = claim.slices();
    let source = match (b.src, src) {
        (0, _) => Source::Empty,
        (_, Some((s, _))) => Source::Other(s),
        _ => Source::InPlace,
    };
    match ptlas::build(&b.input, &ops, mem, source, dst, scratch) {
        Ok(_) => true,
        Err(e) => {
            diag::report(diag::Level::Error, CMD, &format!("{}; build skipped, the destination marked invalid", describe(&e)));
            false
        }
    }
}

fn describe(e: &ptlas::PtlasError) -> String {
    use ptlas::PtlasError as E;
    let op = |o: &u32| ["WRITE_INSTANCE", "UPDATE_INSTANCE", "WRITE_PARTITION_TRANSLATION"].get(*o as usize).copied().unwrap_or("?");
    match e {
        E::InstanceIndex { op: o, record, index } => {
            format!("{} record {record}: instanceIndex {index} is not below input.instanceCount (VUID 10568)", op(o))
        }
        E::PartitionIndex { op: o, record, index } => format!("{} record {record}: partitionIndex {index} is not below input.partitionCount", op(o)),
        E::PartitionFull { record, partition } => {
            format!("WRITE_INSTANCE record {record}: partition {partition} would hold more than maxInstancePerPartitionCount (or maxInstanceInGlobalPartitionCount) instances")
        }
        E::TranslationNotEnabled { record } => format!("WRITE_PARTITION_TRANSLATION record {record}: the structure was built without enablePartitionTranslation"),
        E::InvalidSource => "srcAccelerationStructureData holds no valid partitioned acceleration structure".into(),
        other => format!("{other:?}"),
    }
}
