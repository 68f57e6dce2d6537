//! Memory ops of the SIMD code, lane by lane: the lane frame, push constants and buffers whose
//! bytes the memory exposes (`Memory::host_span`) inline when in bounds, everything else (and
//! every fault) through the scalar JIT's helpers, so values and fault records are the
//! interpreter's.
use cranelift_codegen::ir::condcodes::IntCC;
use cranelift_codegen::ir::{InstBuilder, MemFlagsData, Value};

use super::super::super::ir::{self, AtomicOp, Sc, Space};
use super::super::helpers::{self, MemDesc, MemKind};
use super::super::codegen::span;
use super::gen::{space_ok, Gen, I32, I64, W};

impl Gen<'_, '_, '_> {
    fn site(&mut self, desc: MemDesc) -> i64 {
        self.descs.push(desc);
        self.descs.len() as i64 - 1
    }

    /// The memory helper for lane `l` at site `d`, when the lane runs (else 0).
    fn lane_call(&mut self, d: i64, l: usize, at: Value, a: Value, b: Value) -> Value {
        let (call_b, join) = (self.b.create_block(), self.b.create_block());
        let out = self.b.append_block_param(join, I64);
        let z = self.b.ins().iconst(I64, 0);
        self.b.ins().brif(self.on[l], call_b, &[], join, &[z.into()]);
        self.b.switch_to_block(call_b);
        let dv = self.b.ins().iconst(I64, d);
        // `helpers` keys its faults by lane group, then this.
        let s = self.fault_progress(l);
        let lane = self.b.ins().iconst(I64, l as i64);
        let run = self.run;
        let v = self.call_int(helpers::mem_lane as *const () as usize, &[run, dv, at, a, b, s, lane]);
        self.b.ins().jump(join, &[v.into()]);
        self.b.switch_to_block(join);
        out
    }

    /// `inline` when `ok`, else the helper for the lane when it runs.
    fn guarded(&mut self, ok: Value, d: i64, l: usize, at: Value, v: Value, inline: impl FnOnce(&mut Self) -> Value) -> Value {
        let (fast, slow, join) = (self.b.create_block(), self.b.create_block(), self.b.create_block());
        let out = self.b.append_block_param(join, I64);
        self.b.ins().brif(ok, fast, &[], slow, &[]);
        self.b.switch_to_block(fast);
        let x = inline(self);
        self.b.ins().jump(join, &[x.into()]);
        self.b.switch_to_block(slow);
        let x = self.lane_call(d, l, at, v, v);
        self.b.ins().jump(join, &[x.into()]);
        self.b.switch_to_block(join);
        out
    }

    /// Whether `size` bytes at `at` lie inside `len` bytes.
    fn in_bounds(&mut self, at: Value, len: Value, size: u32) -> Value {
        let last = self.b.ins().iadd_imm_s(len, -(size as i64));
        let fits = self.b.ins().icmp(IntCC::UnsignedLessThanOrEqual, at, last);
        let room = self.b.ins().icmp_imm_s(IntCC::UnsignedGreaterThanOrEqual, len, size as i64);
        self.b.ins().band(fits, room)
    }

    /// The normalised word `ty` at `p`.
    fn load_at(&mut self, ty: Sc, p: Value, off: i32) -> Value {
        // Buffer words need not be aligned.
        let flags = MemFlagsData::new();
        if ty.size() == 8 {
            return self.b.ins().load(I64, flags, p, off);
        }
        let w = self.b.ins().load(I32, flags, p, off);
        if ty == Sc::Bool {
            let c = self.b.ins().icmp_imm_s(IntCC::NotEqual, w, 0);
            self.b.ins().uextend(I64, c)
        } else {
            self.b.ins().uextend(I64, w)
        }
    }

    pub(super) fn load(&mut self, ty: Sc, space: Space, addr: ir::Reg) -> Option<[Value; W]> {
        space_ok(space)?;
        let d = self.site(MemDesc { ty, space, kind: MemKind::Load });
        let size = ty.size();
        let fs = self.fs;
        if space == Space::Lane {
            if let Some(k) = self.types.konst(addr).filter(|&k| k.checked_add(size as u64).is_some_and(|e| e <= fs as u64)) {
                // Every lane's frame is there: load them all, the blend keeps what is not run.
                let frame = self.frame;
                return Some(std::array::from_fn(|l| self.load_at(ty, frame, (l as u32 * fs + k as u32) as i32)));
            }
        }
        if let (Space::Push, Some(k)) = (space, self.types.konst(addr)) {
            return Some([self.uniform_push(d, ty, k); W]);
        }
        let span = match space {
            Space::Buffer(slot) => Some(span(self.b, self.run, slot)),
            _ => None,
        };
        let z = self.b.ins().iconst(I64, 0);
        Some(std::array::from_fn(|l| {
            let at = self.word(addr, l);
            if let Some((base, len)) = span {
                let ok = self.in_bounds(at, len, size);
                return self.guarded(ok, d, l, at, z, |g| {
                    let p = g.b.ins().iadd(base, at);
                    g.load_at(ty, p, 0)
                });
            }
            match space {
                Space::Lane => {
                    let len = self.b.ins().iconst(I64, fs as i64);
                    let ok = self.in_bounds(at, len, size);
                    let frame = self.frame;
                    self.guarded(ok, d, l, at, z, |g| {
                        let p = g.b.ins().iadd(frame, at);
                        g.load_at(ty, p, (l as u32 * fs) as i32)
                    })
                }
                Space::Push => {
                    let (push, len) = (self.push, self.push_len);
                    let ok = self.in_bounds(at, len, size);
                    self.guarded(ok, d, l, at, z, |g| {
                        let p = g.b.ins().iadd(push, at);
                        g.load_at(ty, p, 0)
                    })
                }
                _ => self.lane_call(d, l, at, z, z),
            }
        }))
    }

    /// A push constant at constant offset `k`: one word for every lane, loaded once. Out of
    /// range, each running lane faults and reads 0, as in the interpreter.
    fn uniform_push(&mut self, d: i64, ty: Sc, k: u64) -> Value {
        let (push, len) = (self.push, self.push_len);
        let at = self.b.ins().iconst(I64, k as i64);
        let ok = self.in_bounds(at, len, ty.size());
        let (fast, slow, join) = (self.b.create_block(), self.b.create_block(), self.b.create_block());
        let out = self.b.append_block_param(join, I64);
        self.b.ins().brif(ok, fast, &[], slow, &[]);
        self.b.switch_to_block(fast);
        let p = self.b.ins().iadd(push, at);
        let x = self.load_at(ty, p, 0);
        self.b.ins().jump(join, &[x.into()]);
        self.b.switch_to_block(slow);
        self.b.set_cold_block(slow);
        let z = self.b.ins().iconst(I64, 0);
        // The block's lanes' truth values are made here, where they are needed (`lane_ops`).
        let outer = self.on;
        for l in 0..W {
            let x = self.lane(self.mask, l);
            self.on[l] = self.b.ins().icmp_imm_s(IntCC::NotEqual, x, 0);
        }
        for l in 0..W {
            self.lane_call(d, l, at, z, z);
        }
        self.on = outer;
        self.b.ins().jump(join, &[z.into()]);
        self.b.switch_to_block(join);
        out
    }

    pub(super) fn store(&mut self, ty: Sc, space: Space, addr: ir::Reg, src: ir::Reg) -> Option<()> {
        space_ok(space)?;
        let d = self.site(MemDesc { ty, space, kind: MemKind::Store });
        let size = ty.size();
        let fs = self.fs;
        // Inline where the bytes are: lane `l`'s frame, or the binding's host span.
        let (base, len, stride) = match space {
            Space::Lane => (self.frame, self.b.ins().iconst(I64, fs as i64), fs),
            Space::Buffer(slot) => {
                let (base, len) = span(self.b, self.run, slot);
                (base, len, 0)
            }
            _ => {
                for l in 0..W {
                    let (at, v) = (self.word(addr, l), self.word(src, l));
                    self.lane_call(d, l, at, v, v);
                }
                return Some(());
            }
        };
        for l in 0..W {
            let (at, v) = (self.word(addr, l), self.word(src, l));
            let ok = self.in_bounds(at, len, size);
            let ok = self.b.ins().band(ok, self.on[l]);
            let (fast, slow, join) = (self.b.create_block(), self.b.create_block(), self.b.create_block());
            self.b.ins().brif(ok, fast, &[], slow, &[]);
            self.b.switch_to_block(fast);
            let p = self.b.ins().iadd(base, at);
            let w = if size == 8 { v } else { self.b.ins().ireduce(I32, v) };
            // Buffer memory may be shared with other threads' workgroups: not `trusted`.
            let flags = if stride == 0 { MemFlagsData::new() } else { MemFlagsData::trusted() };
            self.b.ins().store(flags, w, p, (l as u32 * stride) as i32);
            self.b.ins().jump(join, &[]);
            self.b.switch_to_block(slow);
            // Out of bounds (a fault when the lane runs).
            self.lane_call(d, l, at, v, v);
            self.b.ins().jump(join, &[]);
            self.b.switch_to_block(join);
        }
        Some(())
    }

    #[allow(clippy::too_many_arguments)]
    pub(super) fn atomic(&mut self, op: AtomicOp, ty: Sc, space: Space, dst: ir::Reg, addr: ir::Reg, a: ir::Reg, b: ir::Reg) -> Option<()> {
        space_ok(space)?;
        if space == Space::Lane {
            return None;
        }
        let d = self.site(MemDesc { ty, space, kind: MemKind::Atomic(op) });
        let w = std::array::from_fn(|l| {
            let (at, x, y) = (self.word(addr, l), self.word(a, l), self.word(b, l));
            self.lane_call(d, l, at, x, y)
        });
        self.set_words(dst, w);
        Some(())
    }
}
