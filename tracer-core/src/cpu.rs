//! The instruction set the binaries are built for, checked before `main`.
//!
//! `.cargo/config.toml` builds for x86-64-v3 (AVX2, FMA, BMI1/2: Intel from Haswell, AMD from
//! Excavator): 3–8% less CPU per course scene than baseline x86-64, the same image bits
//! (docs/performance.md). On an older CPU such a binary would die of an illegal instruction
//! somewhere in its first lines; this check, run from the ELF initialisers before anything
//! else of the program, says what is missing and how to build for that machine instead.
//! It is written with integer code and inline assembly only, so that it runs where the rest
//! of the binary cannot.

/// CPUID leaf 1 ECX bits x86-64-v3 needs: FMA, MOVBE, POPCNT, OSXSAVE, AVX, F16C.
const LEAF1_V3: u32 = 1 << 12 | 1 << 22 | 1 << 23 | 1 << 27 | 1 << 28 | 1 << 29;
/// CPUID leaf 7 EBX bits: BMI1, AVX2, BMI2.
const LEAF7_V3: u32 = 1 << 3 | 1 << 5 | 1 << 8;
/// XCR0 bits: the OS saves the SSE and AVX registers.
const XCR0_V3: u64 = 0b110;

/// Whether a CPU runs code compiled for x86-64-v3, from CPUID leaf 1's ECX, leaf 7's EBX and
/// the register state the OS saves (XCR0; None where XGETBV is not available). Plain integer
/// tests: the guard below runs it before the CPU is known to have AVX.
#[inline(always)]
pub fn runs_v3(leaf1_ecx: u32, leaf7_ebx: u32, xcr0: Option<u64>) -> bool {
    let os_saves_avx = match xcr0 {
        Some(x) => x & XCR0_V3 == XCR0_V3,
        None => false,
    };
    leaf1_ecx & LEAF1_V3 == LEAF1_V3 && leaf7_ebx & LEAF7_V3 == LEAF7_V3 && os_saves_avx
}

#[cfg(all(target_arch = "x86_64", target_os = "linux", target_feature = "avx2"))]
mod guard {
    use std::arch::asm;

    /// CPUID leaf `leaf`, subleaf 0: (eax, ebx, ecx). RBX is reserved by LLVM, hence the
    /// swap.
    fn cpuid(leaf: u32) -> (u32, u32, u32) {
        let (eax, ebx, ecx): (u32, u32, u32);
        // SAFETY: CPUID exists on every x86-64 CPU and only writes the named registers.
        unsafe {
            asm!(
                "mov {t:r}, rbx",
                "cpuid",
                "xchg {t:r}, rbx",
                t = out(reg) ebx,
                inout("eax") leaf => eax,
                inout("ecx") 0u32 => ecx,
                out("edx") _,
                options(nomem, nostack, preserves_flags),
            );
        }
        (eax, ebx, ecx)
    }

    const MESSAGE: &[u8] = b"error: this binary is built for x86-64-v3 CPUs (AVX2, FMA, BMI2), \
and this CPU or its OS lacks one of them.\nBuild for it with RUSTFLAGS=\"-C target-cpu=x86-64\" \
(README, \"Performance\"): the images are the same bits.\n";

    /// Writes the message to standard error and ends the process with status 1, by system
    /// calls: the standard library's printing may already use the missing instructions.
    #[inline(always)]
    fn die() -> ! {
        // SAFETY: write(2, ptr, len) reads `len` bytes of a static.
        unsafe {
            asm!(
                "syscall",
                inout("rax") 1usize => _,
                in("rdi") 2usize,
                in("rsi") MESSAGE.as_ptr(),
                in("rdx") MESSAGE.len(),
                out("rcx") _,
                out("r11") _,
                options(nostack, readonly),
            );
        }
        // SAFETY: exit_group(1) does not return.
        unsafe {
            asm!("syscall", in("rax") 231usize, in("rdi") 1usize, options(noreturn, nostack));
        }
    }

    extern "C" fn check() {
        let (max_leaf, _, _) = cpuid(0);
        let (_, _, leaf1_ecx) = cpuid(1);
        // A CPU without leaf 7 has none of its features.
        let leaf7_ebx = if max_leaf >= 7 { cpuid(7).1 } else { 0 };
        let xcr0 = (leaf1_ecx >> 27 & 1 == 1).then(|| {
            let (lo, hi): (u32, u32);
            // SAFETY: XGETBV is available once OSXSAVE is set (checked above).
            unsafe {
                asm!("xgetbv", in("ecx") 0u32, out("eax") lo, out("edx") hi, options(nomem, nostack));
            }
            (hi as u64) << 32 | lo as u64
        });
        if !super::runs_v3(leaf1_ecx, leaf7_ebx, xcr0) {
            die();
        }
    }

    /// Run by the dynamic loader before `main` and before the standard library's start-up.
    #[used]
    #[unsafe(link_section = ".init_array")]
    static CHECK: extern "C" fn() = check;
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_v3_cpu_passes_and_any_missing_feature_fails() {
        assert!(runs_v3(LEAF1_V3, LEAF7_V3, Some(0b111)));
        for bit in 0..32 {
            if LEAF1_V3 >> bit & 1 == 1 {
                assert!(
                    !runs_v3(LEAF1_V3 & !(1 << bit), LEAF7_V3, Some(0b111)),
                    "leaf 1 bit {bit}"
                );
            }
            if LEAF7_V3 >> bit & 1 == 1 {
                assert!(
                    !runs_v3(LEAF1_V3, LEAF7_V3 & !(1 << bit), Some(0b111)),
                    "leaf 7 bit {bit}"
                );
            }
        }
        // An OS that does not save the AVX registers, or no XGETBV.
        assert!(!runs_v3(LEAF1_V3, LEAF7_V3, Some(0b011)));
        assert!(!runs_v3(LEAF1_V3, LEAF7_V3, None));
        // A Sandy Bridge: AVX without FMA, F16C, AVX2 or BMI.
        assert!(!runs_v3(1 << 23 | 1 << 27 | 1 << 28, 0, Some(0b111)));
    }
}
