//! FNV-1a (64 bit): the one small, stable, non-cryptographic hash the crate uses
//! (MPI ranks' parameter checks, the ONNX sidecar's config hash, the experiment's
//! per-cell bootstrap seeds). Stable across Rust versions, unlike `std`'s hasher.

/// FNV-1a's initial state (the "offset basis").
pub const FNV1A64_OFFSET: u64 = 0xcbf2_9ce4_8422_2325;
const FNV1A64_PRIME: u64 = 0x0100_0000_01b3;

/// FNV-1a of `bytes`, continuing from `state`.
pub fn fnv1a64_from(state: u64, bytes: impl IntoIterator<Item = u8>) -> u64 {
    bytes
        .into_iter()
        .fold(state, |h, b| (h ^ u64::from(b)).wrapping_mul(FNV1A64_PRIME))
}

/// FNV-1a of `bytes`.
pub fn fnv1a64(bytes: impl IntoIterator<Item = u8>) -> u64 {
    fnv1a64_from(FNV1A64_OFFSET, bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn known_values() {
        // the published FNV-1a 64 test vectors
        assert_eq!(fnv1a64(*b""), 0xcbf2_9ce4_8422_2325);
        assert_eq!(fnv1a64(*b"a"), 0xaf63_dc4c_8601_ec8c);
        assert_eq!(fnv1a64(*b"foobar"), 0x8594_4171_f739_67e8);
    }
}
