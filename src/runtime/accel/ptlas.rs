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

/// The recorded command.
pub struct PtlasCommand {
    pub build: PtlasBuild,
}

impl Exec for PtlasCommand {
    fn name(&self) -> &'static str {
        CMD
    }
    fn execute(&self, ctx: &ExecContext<'_>) -> Result<(), ExecError> {
        if !ctx.device.extension_enabled(EXTENSION) {
            diag::vuid("VUID-vkCmdBuildPartitionedAccelerationStructuresNV-partitionedAccelerationStructure-10536", CMD, "VK_NV_partitioned_acceleration_structure is not enabled");
        }
        let inputs = DeviceInputs::new(ctx.memory(), CMD);
        let ok = crate::threads::run_parallel(false, || execute(&inputs, &self.build));
        if !ok && diag::strict() {
            return Err(ExecError::Invalid { vuid: "strict", message: "a partitioned acceleration-structure build broke a valid-usage rule (ARBOR_STRICT)".into() });
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

/// Device bytes an input lives in: a usage mismatch is reported (real clients commit it) and
/// the bytes are read anyway; an unresolvable range is reported and gives None.
fn read_input<'m>(mem: &'m DeviceInputs<'_>, address: u64, len: u64, what: &str) -> Option<&'m [u8]> {
    match mem.input(address, len, vk::BufferUsageFlags::ACCELERATION_STRUCTURE_BUILD_INPUT_READ_ONLY_KHR) {
        Ok(b) => Some(b),
        Err(InputError::Usage(u)) => {
            diag::report(diag::Level::Warn, CMD, &format!("[{}] {what} lies in a buffer without ACCELERATION_STRUCTURE_BUILD_INPUT_READ_ONLY_BIT_KHR (has {u:?})", vuid_name(10551)));
            mem.view.bytes(address, len)
        }
        Err(e) => {
            diag::report(diag::Level::Error, CMD, &format!("{what} at {address:#x} ({len} bytes) does not resolve: {e}; build skipped"));
            None
        }
    }
}

/// The op records of one build: the count, then each command's strided records.
fn read_ops<'m>(mem: &'m DeviceInputs<'_>, b: &PtlasBuild) -> Option<Ops<'m>> {
    if !b.src_infos_count.is_multiple_of(4) {
        diag::report(diag::Level::Error, CMD, "srcInfosCount is not aligned to 4 bytes; build skipped");
        return None;
    }
    let count = u32::from_le_bytes(read_input(mem, b.src_infos_count, 4, "the srcInfosCount word")?.try_into().ok()?);
    let mut ops = Ops::default();
    if count == 0 {
        return Some(ops);
    }
    if count > 3 {
        diag::report(diag::Level::Error, CMD, &format!("srcInfosCount is {count}: more op records than op types (each may appear once); build skipped"));
        return None;
    }
    let size = std::mem::size_of::<IndirectCommand>() as u64;
    let infos = read_input(mem, b.src_infos, size * count as u64, "the srcInfos array")?;
    let mut seen = [false; 3];
    for k in 0..count {
        let cmd: IndirectCommand = Strided { data: infos, count, stride: size }.get(k)?;
        let op = cmd.op_type as usize;
        if op > 2 || seen[op] {
            let msg = format!("srcInfos[{k}].opType {} is unknown or repeats an earlier element's (each element must have a distinct opType); build skipped", cmd.op_type);
            diag::report(diag::Level::Error, CMD, &msg);
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
        let data = if span == 0 { &[][..] } else { read_input(mem, cmd.start_address, span, &format!("srcInfos[{k}].argData"))? };
        let s = Strided { data, count: cmd.arg_count, stride };
        match op {
            0 => ops.writes = s,
            1 => ops.updates = s,
            _ => ops.translations = s,
        }
    }
    Some(ops)
}

fn overlaps(a: u64, alen: u64, b: u64, blen: u64) -> bool {
    a < b.saturating_add(blen) && b < a.saturating_add(alen)
}

/// A source blob's bytes and its used size.
type SourceBytes<'m> = Option<(&'m [u8], u64)>;

/// The source's bytes (with its used size) when it is another blob, and how many bytes of dst
/// the build may use: up to the layout of a grown source, at least `needed`. None: reported.
fn source_and_destination<'m>(mem: &'m DeviceInputs<'_>, b: &PtlasBuild, needed: u64) -> Option<(SourceBytes<'m>, u64)> {
    let header_at = |address: u64| mem.view.bytes(address, ptlas::HEADER_SIZE as u64).and_then(ptlas::header);
    let src = if b.src == 0 || b.src == b.dst {
        None
    } else {
        let used = header_at(b.src).map(|h| h.used_size);
        match used.and_then(|u| mem.view.bytes(b.src, u).map(|s| (s, u))) {
            Some(s) => Some(s),
            None => {
                diag::report(diag::Level::Error, CMD, &format!("srcAccelerationStructureData {:#x} holds no valid partitioned acceleration structure; build skipped", b.src));
                return None;
            }
        }
    };
    // dst may be laid out for a grown source's capacities: give it what its buffer holds, up to that.
    let prior = if b.src == 0 { None } else { header_at(b.src) };
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
        diag::vuid(&vuid_name(10543), CMD, &format!("dstAccelerationStructureData has {room} bytes; the build needs {needed}; build skipped"));
        return None;
    }
    Some((src, want.min(room)))
}

/// Checks, then runs one build. Returns false when anything was invalid (reported once).
fn execute(mem: &DeviceInputs<'_>, b: &PtlasBuild) -> bool {
    for (address, n, what) in [(b.scratch, 10542, "scratchData"), (b.src, 10544, "srcAccelerationStructureData"), (b.dst, 10545, "dstAccelerationStructureData")] {
        if !address.is_multiple_of(PTLAS_ALIGNMENT) {
            diag::vuid(&vuid_name(n), CMD, &format!("{what} {address:#x} is not aligned to 256 bytes; build skipped"));
            return false;
        }
    }
    let Some(ops) = read_ops(mem, b) else { return false };
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
            diag::report(diag::Level::Error, CMD, &format!("dstAccelerationStructureData does not resolve ({e}); build skipped"));
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
