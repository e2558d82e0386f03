//! A hint to the processor to bring a value into its caches before it is read. The refraction
//! term's trace asks for the plane and corners of the triangle a ray a few places ahead has hit
//! while it refracts the current one (`bench gradient`, CHANGELOG 0.27.3). A hint only: it
//! changes no result, and on processors other than x86-64 it does nothing.

/// Asks for the cache lines that hold `x` (its first and last byte) to be fetched.
#[inline(always)]
pub fn prefetch<T>(x: &T) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: a prefetch reads nothing the program sees and cannot fault (and `x` is a valid
    // reference); the intrinsic is `unsafe` only as an SSE function, and SSE is part of
    // x86-64.
    #[allow(unsafe_code)]
    unsafe {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        let first = (x as *const T).cast::<i8>();
        let last = first.wrapping_add(std::mem::size_of::<T>().saturating_sub(1));
        _mm_prefetch::<_MM_HINT_T0>(first);
        _mm_prefetch::<_MM_HINT_T0>(last);
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = x;
}
