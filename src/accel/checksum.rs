//! The integrity checksum of a stored structure: a 64-bit hash (four-lane multiply-rotate
//! rounds in the style of xxHash64, written here) over every used byte except the checksum
//! field itself and the BLAS address table, which applications rewrite when they relocate a
//! serialized TLAS (its entries are checked one by one instead).
//!
//! Owns: the hash and which bytes it covers. Must not touch: anything but the bytes it reads
//! and the checksum field it writes. The value is a function of the bytes alone: chunks are
//! hashed in parallel and their hashes combined in order, so the thread count never changes it.
use super::layout::{self, RawHeader, HEADER_SIZE};
use rayon::prelude::*;

const P1: u64 = 0x9E37_79B1_85EB_CA87;
const P2: u64 = 0xC2B2_AE3D_27D4_EB4F;
const P3: u64 = 0x1656_67B1_9E37_79F9;
const P4: u64 = 0x85EB_CA77_C2B2_AE63;
const P5: u64 = 0x27D4_EB2F_1656_67C5;

/// Bytes per parallel task: large enough that a task is worth its hand-off.
const CHUNK: usize = 1 << 20;

#[inline(always)]
fn round(acc: u64, lane: u64) -> u64 {
    acc.wrapping_add(lane.wrapping_mul(P2)).rotate_left(31).wrapping_mul(P1)
}

#[inline(always)]
fn avalanche(mut h: u64) -> u64 {
    h ^= h >> 33;
    h = h.wrapping_mul(P2);
    h ^= h >> 29;
    h = h.wrapping_mul(P3);
    h ^ (h >> 32)
}

fn lane(b: &[u8]) -> u64 {
    let mut w = [0u8; 8];
    w[..b.len().min(8)].copy_from_slice(&b[..b.len().min(8)]);
    u64::from_le_bytes(w)
}

/// The hash of one slice, seeded.
pub fn hash(bytes: &[u8], seed: u64) -> u64 {
    let mut acc = [seed.wrapping_add(P1).wrapping_add(P2), seed.wrapping_add(P2), seed, seed.wrapping_sub(P1)];
    let mut blocks = bytes.chunks_exact(32);
    for b in &mut blocks {
        // Whole-word loads: the block is known to hold four words (`lane` pads a short tail).
        let w = |k: usize| b.get(8 * k..8 * k + 8).and_then(|x| x.try_into().ok()).map_or(0, u64::from_le_bytes);
        for (k, a) in acc.iter_mut().enumerate() {
            *a = round(*a, w(k));
        }
    }
    let mut h = acc[0].rotate_left(1).wrapping_add(acc[1].rotate_left(7)).wrapping_add(acc[2].rotate_left(12)).wrapping_add(acc[3].rotate_left(18));
    for a in acc {
        h = (h ^ round(0, a)).wrapping_mul(P1).wrapping_add(P4);
    }
    h = h.wrapping_add(bytes.len() as u64);
    for w in blocks.remainder().chunks(8) {
        h = (h ^ round(0, lane(w))).rotate_left(27).wrapping_mul(P1).wrapping_add(P4);
    }
    avalanche(h ^ P5)
}

/// The hash of a long slice: its chunks hashed in parallel, their hashes combined in order.
fn hash_long(bytes: &[u8], seed: u64) -> u64 {
    if bytes.len() <= CHUNK {
        return hash(bytes, seed);
    }
    let parts: Vec<u64> = bytes.par_chunks(CHUNK).map(|c| hash(c, seed)).collect();
    hash(bytemuck::cast_slice(&parts), seed ^ bytes.len() as u64)
}

/// The checksum of a structure whose header is `raw` and whose used bytes are `bytes`:
/// the header with its checksum field zeroed, then every section except the BLAS table.
pub fn structure_checksum(raw: &RawHeader, bytes: &[u8]) -> u64 {
    let used = (raw.used_size as usize).min(bytes.len());
    let table = if raw.ty == super::AsType::TopLevel as u32 {
        let start = (raw.blas_table_offset as usize).clamp(HEADER_SIZE, used);
        let end = start.saturating_add(raw.blas_table_capacity as usize * 8).min(used);
        start..end
    } else {
        used..used
    };
    let parts = [HEADER_SIZE.min(used)..table.start, table.end..used].map(|r| &bytes[r]);
    combine(raw, [part_hash(parts[0], 0), part_hash(parts[1], 1)])
}

/// The hash of part `i` of a structure's checksummed bytes: part 0 runs from the header's end
/// to the BLAS table, part 1 from the table's end to the used size (BLAS: the table is empty
/// and sits at the used size). A TLAS build hashes each part as soon as it is written.
pub fn part_hash(bytes: &[u8], i: usize) -> u64 {
    hash_long(bytes, i as u64 + 1)
}

/// The checksum of the structure whose header is `raw` and whose parts hash to `parts`.
pub fn combine(raw: &RawHeader, parts: [u64; 2]) -> u64 {
    let mut head = *raw;
    head.checksum = 0;
    let mut h = hash(bytemuck::bytes_of(&head), 0);
    for p in parts {
        h = hash(&[h.to_le_bytes(), p.to_le_bytes()].concat(), 0);
    }
    h
}

/// Writes the checksum of the structure in `dst` (a valid header) into its header.
pub fn seal(dst: &mut [u8]) {
    let Some(p) = layout::parse(dst) else { return };
    let mut raw = p.raw;
    raw.checksum = structure_checksum(&raw, p.bytes);
    layout::write_header(dst, &raw);
}

/// Writes the checksum of the structure in `dst` (a valid header) from its parts' hashes
/// (`part_hash`, computed where the parts were written).
pub fn seal_parts(dst: &mut [u8], parts: [u64; 2]) {
    let Some(p) = layout::parse(dst) else { return };
    let mut raw = p.raw;
    raw.checksum = combine(&raw, parts);
    layout::write_header(dst, &raw);
}

/// Whether the stored checksum matches the bytes.
pub fn verify(raw: &RawHeader, bytes: &[u8]) -> bool {
    structure_checksum(raw, bytes) == raw.checksum
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `hash` against a plain transcription of its definition: little-endian words taken byte
    /// by byte, four lanes over 32-byte blocks, then the tail in zero-padded words.
    #[test]
    fn hash_matches_a_bytewise_reference() {
        let word = |b: &[u8]| b.iter().rev().fold(0u64, |w, &x| w << 8 | x as u64);
        let reference = |bytes: &[u8], seed: u64| {
            let mut acc = [seed.wrapping_add(P1).wrapping_add(P2), seed.wrapping_add(P2), seed, seed.wrapping_sub(P1)];
            let whole = bytes.len() / 32 * 32;
            for block in bytes[..whole].chunks(32) {
                for k in 0..4 {
                    acc[k] = acc[k].wrapping_add(word(&block[8 * k..8 * k + 8]).wrapping_mul(P2)).rotate_left(31).wrapping_mul(P1);
                }
            }
            let mut h = acc[0].rotate_left(1).wrapping_add(acc[1].rotate_left(7)).wrapping_add(acc[2].rotate_left(12)).wrapping_add(acc[3].rotate_left(18));
            for a in acc {
                h = (h ^ a.wrapping_mul(P2).rotate_left(31).wrapping_mul(P1)).wrapping_mul(P1).wrapping_add(P4);
            }
            h = h.wrapping_add(bytes.len() as u64);
            for w in bytes[whole..].chunks(8) {
                h = (h ^ word(w).wrapping_mul(P2).rotate_left(31).wrapping_mul(P1)).rotate_left(27).wrapping_mul(P1).wrapping_add(P4);
            }
            h ^= P5;
            h ^= h >> 33;
            h = h.wrapping_mul(P2);
            h ^= h >> 29;
            h = h.wrapping_mul(P3);
            h ^ (h >> 32)
        };
        let mut next = crate::accel::testing::xorshift(3);
        let bytes: Vec<u8> = (0..1000).map(|_| next() as u8).collect();
        for len in [0, 1, 7, 8, 31, 32, 33, 64, 100, 255, 1000] {
            for seed in [0, 1, 0xDEAD_BEEF] {
                assert_eq!(hash(&bytes[..len], seed), reference(&bytes[..len], seed), "len {len} seed {seed}");
            }
        }
    }
}
