//! Valid usage of one build's op records, checked before anything is written: the rules of
//! VkPartitionedAccelerationStructureWriteInstanceDataNV, …UpdateInstanceDataNV,
//! …WritePartitionTranslationDataNV and VkBuildPartitionedAccelerationStructureIndirectCommandNV
//! that depend only on the records and the build's input. A build whose records break one is
//! refused whole, so a refused build leaves its destination untouched by the library.
//!
//! Owns: the rules and their VUIDs. Must not touch: device memory or diagnostics (the caller
//! reads the records and reports what this returns), the blob.
use super::{Input, Ops, Strided, UpdateInstance, WriteInstance, WriteTranslation};
use super::{INSTANCE_FLAG_EXPLICIT_BOUNDING_BOX, OP_UPDATE_INSTANCE, OP_WRITE_INSTANCE, OP_WRITE_PARTITION_TRANSLATION, PARTITION_INDEX_GLOBAL};

/// Every defined VkPartitionedAccelerationStructureInstanceFlagBitsNV bit.
pub const INSTANCE_FLAGS_ALL: u32 = 0x1f;

/// One broken rule: its VUID (None where no numbered VUID names it) and what was found.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RecordViolation {
    pub vuid: Option<&'static str>,
    pub message: String,
}

/// What the records do that is valid Vulkan usage but that other APIs of the same driver
/// feature forbid (reported as a note; the build runs).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct RecordNotes {
    /// Instance indices that a WRITE_INSTANCE and an UPDATE_INSTANCE of this build both name
    /// (NVAPI allows one write or update per instance per build; Vulkan only one per array).
    pub written_and_updated: Vec<u32>,
}

fn op_name(op: u32) -> &'static str {
    ["WRITE_INSTANCE", "UPDATE_INSTANCE", "WRITE_PARTITION_TRANSLATION"].get(op as usize).copied().unwrap_or("?")
}

fn violation(vuid: &'static str, op: u32, record: u32, what: String) -> RecordViolation {
    RecordViolation { vuid: Some(vuid), message: format!("{} record {record}: {what}", op_name(op)) }
}

fn record<T: bytemuck::Pod>(s: &Strided, op: u32, k: u32) -> Result<T, RecordViolation> {
    s.get(k).ok_or_else(|| RecordViolation { vuid: None, message: format!("{} record {k} lies outside its argData range", op_name(op)) })
}

/// The first record index (in record order) naming an instance an earlier record named.
fn repeated(indices: &[u32]) -> Option<(u32, u32)> {
    let mut sorted: Vec<(u32, u32)> = indices.iter().enumerate().map(|(k, &i)| (i, k as u32)).collect();
    sorted.sort_unstable();
    sorted.windows(2).filter(|w| w[0].0 == w[1].0).map(|w| (w[1].1, w[0].0)).min_by_key(|&(k, _)| k)
}

fn valid_box(b: &[f32; 6]) -> bool {
    b.iter().all(|x| !x.is_nan()) && b[0] <= b[3] && b[1] <= b[4] && b[2] <= b[5]
}

fn check_write(input: &Input, k: u32, w: &WriteInstance) -> Result<(), RecordViolation> {
    let op = OP_WRITE_INSTANCE;
    if w.instance_index >= input.instance_count {
        let what = format!("instanceIndex {} is not below input.instanceCount {}", w.instance_index, input.instance_count);
        return Err(violation("VUID-VkPartitionedAccelerationStructureWriteInstanceDataNV-instanceIndex-10568", op, k, what));
    }
    if w.partition_index != PARTITION_INDEX_GLOBAL && w.partition_index >= input.partition_count {
        let what = format!("partitionIndex {} is not below input.partitionCount {} (nor the global partition)", w.partition_index, input.partition_count);
        return Err(violation("VUID-VkPartitionedAccelerationStructureWriteInstanceDataNV-partitionIndex-10569", op, k, what));
    }
    if w.instance_mask >> 8 != 0 {
        return Err(violation("VUID-VkPartitionedAccelerationStructureWriteInstanceDataNV-instanceMask-10566", op, k, format!("instanceMask {:#x} has bits above the low 8", w.instance_mask)));
    }
    if w.instance_contribution_to_hit_group_index >> 24 != 0 {
        let what = format!("instanceContributionToHitGroupIndex {:#x} has bits above the low 24", w.instance_contribution_to_hit_group_index);
        return Err(violation("VUID-VkPartitionedAccelerationStructureWriteInstanceDataNV-instanceContributionToHitGroupIndex-10567", op, k, what));
    }
    if w.instance_flags & !INSTANCE_FLAGS_ALL != 0 {
        return Err(violation("VUID-VkPartitionedAccelerationStructureWriteInstanceDataNV-instanceFlags-parameter", op, k, format!("instanceFlags {:#x} has undefined bits", w.instance_flags)));
    }
    if w.instance_flags & INSTANCE_FLAG_EXPLICIT_BOUNDING_BOX != 0 && !valid_box(&w.explicit_aabb) {
        return Err(violation("VUID-VkPartitionedAccelerationStructureWriteInstanceDataNV-explicitAABB-10570", op, k, format!("explicitAABB {:?} is not a valid box (min > max or NaN)", w.explicit_aabb)));
    }
    Ok(())
}

fn check_update(input: &Input, k: u32, u: &UpdateInstance) -> Result<(), RecordViolation> {
    let op = OP_UPDATE_INSTANCE;
    if u.instance_index >= input.instance_count {
        let what = format!("instanceIndex {} is not below input.instanceCount {}", u.instance_index, input.instance_count);
        return Err(violation("VUID-VkPartitionedAccelerationStructureUpdateInstanceDataNV-instanceIndex-10573", op, k, what));
    }
    if u.instance_contribution_to_hit_group_index >> 24 != 0 {
        let what = format!("instanceContributionToHitGroupIndex {:#x} has bits above the low 24", u.instance_contribution_to_hit_group_index);
        return Err(violation("VUID-VkPartitionedAccelerationStructureUpdateInstanceDataNV-instanceContributionToHitGroupIndex-10571", op, k, what));
    }
    Ok(())
}

fn check_translation(input: &Input, k: u32, t: &WriteTranslation) -> Result<(), RecordViolation> {
    let op = OP_WRITE_PARTITION_TRANSLATION;
    if !input.translation {
        return Err(violation("VUID-VkPartitionedAccelerationStructureWritePartitionTranslationDataNV-enablePartitionTranslation-10575", op, k, "the build's input lacks enablePartitionTranslation".into()));
    }
    if t.partition_index != PARTITION_INDEX_GLOBAL && t.partition_index >= input.partition_count {
        let what = format!("partitionIndex {} is not below input.partitionCount {} (nor the global partition)", t.partition_index, input.partition_count);
        return Err(violation("VUID-VkPartitionedAccelerationStructureWritePartitionTranslationDataNV-partitionIndex-10574", op, k, what));
    }
    Ok(())
}

const DUPLICATE: &str = "VUID-VkBuildPartitionedAccelerationStructureIndirectCommandNV-argData-10565";

/// Checks every record of `ops` against `input`. Err: the first broken rule (records in order:
/// writes, updates, translations); Ok: the notes on valid but questionable use.
pub fn check_ops(input: &Input, ops: &Ops) -> Result<RecordNotes, RecordViolation> {
    let mut written = Vec::with_capacity(ops.writes.count as usize);
    for k in 0..ops.writes.count {
        let w: WriteInstance = record(&ops.writes, OP_WRITE_INSTANCE, k)?;
        check_write(input, k, &w)?;
        written.push(w.instance_index);
    }
    if let Some((k, index)) = repeated(&written) {
        return Err(violation(DUPLICATE, OP_WRITE_INSTANCE, k, format!("instanceIndex {index} is named by an earlier record of the same argData")));
    }
    let mut updated = Vec::with_capacity(ops.updates.count as usize);
    for k in 0..ops.updates.count {
        let u: UpdateInstance = record(&ops.updates, OP_UPDATE_INSTANCE, k)?;
        check_update(input, k, &u)?;
        updated.push(u.instance_index);
    }
    if let Some((k, index)) = repeated(&updated) {
        return Err(violation(DUPLICATE, OP_UPDATE_INSTANCE, k, format!("instanceIndex {index} is named by an earlier record of the same argData")));
    }
    for k in 0..ops.translations.count {
        let t: WriteTranslation = record(&ops.translations, OP_WRITE_PARTITION_TRANSLATION, k)?;
        check_translation(input, k, &t)?;
    }
    let mut notes = RecordNotes::default();
    if !written.is_empty() && !updated.is_empty() {
        written.sort_unstable();
        updated.sort_unstable();
        updated.dedup();
        notes.written_and_updated = updated.into_iter().filter(|i| written.binary_search(i).is_ok()).collect();
    }
    Ok(notes)
}

#[cfg(test)]
mod tests {
    use super::*;
    use bytemuck::Zeroable;

    fn input() -> Input {
        Input { instance_count: 8, max_instance_per_partition_count: 8, partition_count: 2, max_instance_in_global_partition_count: 8, ..Input::default() }
    }

    fn write(index: u32) -> WriteInstance {
        WriteInstance { instance_index: index, instance_mask: 0xff, ..WriteInstance::zeroed() }
    }

    fn check_writes(ws: &[WriteInstance]) -> Result<RecordNotes, RecordViolation> {
        let bytes: &[u8] = bytemuck::cast_slice(ws);
        check_ops(&input(), &Ops { writes: Strided { data: bytes, count: ws.len() as u32, stride: 0 }, ..Ops::default() })
    }

    fn vuid_of(r: Result<RecordNotes, RecordViolation>) -> Option<&'static str> {
        r.err().and_then(|v| v.vuid)
    }

    #[test]
    fn each_write_rule_names_its_vuid() {
        assert_eq!(check_writes(&[write(0), write(7)]), Ok(RecordNotes::default()));
        let cases: [(WriteInstance, &str); 7] = [
            (write(8), "instanceIndex-10568"),
            (WriteInstance { partition_index: 2, ..write(0) }, "partitionIndex-10569"),
            (WriteInstance { instance_mask: 0x100, ..write(0) }, "instanceMask-10566"),
            (WriteInstance { instance_contribution_to_hit_group_index: 1 << 24, ..write(0) }, "instanceContributionToHitGroupIndex-10567"),
            (WriteInstance { instance_flags: 0x20, ..write(0) }, "instanceFlags-parameter"),
            (WriteInstance { instance_flags: 0x10, explicit_aabb: [1.0, 0.0, 0.0, 0.0, 1.0, 1.0], ..write(0) }, "explicitAABB-10570"),
            (WriteInstance { instance_flags: 0x10, explicit_aabb: [0.0, f32::NAN, 0.0, 1.0, 1.0, 1.0], ..write(0) }, "explicitAABB-10570"),
        ];
        for (w, suffix) in cases {
            let v = vuid_of(check_writes(&[write(1), w])).unwrap_or("none");
            assert!(v.starts_with("VUID-VkPartitionedAccelerationStructureWriteInstanceDataNV-") && v.ends_with(suffix), "{suffix}: got {v}");
        }
        // The global partition is no partition index out of range.
        assert!(check_writes(&[WriteInstance { partition_index: PARTITION_INDEX_GLOBAL, ..write(0) }]).is_ok());
    }

    #[test]
    fn repeated_instances_name_the_later_record() {
        let v = check_writes(&[write(3), write(1), write(5), write(1)]).unwrap_err();
        assert_eq!(v.vuid, Some(DUPLICATE));
        assert!(v.message.starts_with("WRITE_INSTANCE record 3:"), "{}", v.message);
        let u = [UpdateInstance { instance_index: 2, ..UpdateInstance::zeroed() }; 2];
        let ops = Ops { updates: Strided { data: bytemuck::cast_slice(&u), count: 2, stride: 0 }, ..Ops::default() };
        assert_eq!(check_ops(&input(), &ops).unwrap_err().vuid, Some(DUPLICATE));
    }

    #[test]
    fn update_and_translation_rules_and_the_write_update_note() {
        let ws = [write(2), write(4)];
        let us = [UpdateInstance { instance_index: 4, ..UpdateInstance::zeroed() }, UpdateInstance { instance_index: 6, ..UpdateInstance::zeroed() }];
        let ops = Ops {
            writes: Strided { data: bytemuck::cast_slice(&ws), count: 2, stride: 0 },
            updates: Strided { data: bytemuck::cast_slice(&us), count: 2, stride: 0 },
            ..Ops::default()
        };
        assert_eq!(check_ops(&input(), &ops).unwrap().written_and_updated, vec![4]);
        let bad = [UpdateInstance { instance_index: 8, ..UpdateInstance::zeroed() }];
        let ops = Ops { updates: Strided { data: bytemuck::cast_slice(&bad), count: 1, stride: 0 }, ..Ops::default() };
        assert!(check_ops(&input(), &ops).unwrap_err().vuid.unwrap().ends_with("instanceIndex-10573"));
        let t = [WriteTranslation { partition_index: 1, partition_translation: [1.0; 3] }];
        let ops = Ops { translations: Strided { data: bytemuck::cast_slice(&t), count: 1, stride: 0 }, ..Ops::default() };
        assert!(check_ops(&input(), &ops).unwrap_err().vuid.unwrap().ends_with("enablePartitionTranslation-10575"));
        let with = Input { translation: true, ..input() };
        assert!(check_ops(&with, &ops).is_ok());
        let t = [WriteTranslation { partition_index: 2, partition_translation: [1.0; 3] }];
        let ops = Ops { translations: Strided { data: bytemuck::cast_slice(&t), count: 1, stride: 0 }, ..Ops::default() };
        assert!(check_ops(&with, &ops).unwrap_err().vuid.unwrap().ends_with("partitionIndex-10574"));
    }
}
