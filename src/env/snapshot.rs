//! A small byte codec for state a resumed run restores bit for bit (env
//! episodes, RNG positions, curriculum): little-endian values, slices with
//! their length, read back with every length and tag checked, so that a
//! mismatched or damaged snapshot is an error, never a panic.

use anyhow::{bail, ensure, Context, Result};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// Appends values to a byte buffer.
#[derive(Default)]
pub struct StateWriter {
    buf: Vec<u8>,
}

impl StateWriter {
    pub fn new(tag: &str) -> StateWriter {
        let mut w = StateWriter::default();
        w.str(tag);
        w
    }
    pub fn into_bytes(self) -> Vec<u8> {
        self.buf
    }
    pub fn u64(&mut self, v: u64) {
        self.buf.extend_from_slice(&v.to_le_bytes());
    }
    pub fn usize(&mut self, v: usize) {
        self.u64(v as u64);
    }
    pub fn f64(&mut self, v: f64) {
        self.u64(v.to_bits());
    }
    pub fn f64s(&mut self, v: &[f64]) {
        self.usize(v.len());
        v.iter().for_each(|x| self.f64(*x));
    }
    pub fn f32s(&mut self, v: &[f32]) {
        self.usize(v.len());
        for x in v {
            self.buf.extend_from_slice(&x.to_bits().to_le_bytes());
        }
    }
    pub fn bytes(&mut self, v: &[u8]) {
        self.usize(v.len());
        self.buf.extend_from_slice(v);
    }
    pub fn str(&mut self, v: &str) {
        self.bytes(v.as_bytes());
    }
    /// A ChaCha8 generator's whole state (seed, stream, word position).
    pub fn rng(&mut self, r: &ChaCha8Rng) {
        self.buf.extend_from_slice(&r.get_seed());
        self.u64(r.get_stream());
        self.buf.extend_from_slice(&r.get_word_pos().to_le_bytes());
    }
}

/// Reads what a [`StateWriter`] wrote, in the same order.
pub struct StateReader<'a> {
    data: &'a [u8],
    at: usize,
}

impl<'a> StateReader<'a> {
    /// Starts reading `data`, which must begin with `tag`.
    pub fn new(data: &'a [u8], tag: &str) -> Result<StateReader<'a>> {
        let mut r = StateReader { data, at: 0 };
        let found = r.bytes().context("reading the snapshot's tag")?;
        ensure!(
            found == tag.as_bytes(),
            "a snapshot tagged {:?} where {tag:?} was expected",
            String::from_utf8_lossy(found)
        );
        Ok(r)
    }
    fn take(&mut self, n: usize) -> Result<&'a [u8]> {
        let end = self.at.checked_add(n).filter(|&e| e <= self.data.len());
        let Some(end) = end else {
            bail!(
                "the snapshot ends early ({} bytes, {n} more wanted at byte {})",
                self.data.len(),
                self.at
            );
        };
        let out = &self.data[self.at..end];
        self.at = end;
        Ok(out)
    }
    pub fn u64(&mut self) -> Result<u64> {
        Ok(u64::from_le_bytes(self.take(8)?.try_into()?))
    }
    pub fn usize(&mut self) -> Result<usize> {
        Ok(usize::try_from(self.u64()?)?)
    }
    pub fn f64(&mut self) -> Result<f64> {
        Ok(f64::from_bits(self.u64()?))
    }
    fn len(&mut self, expected: Option<usize>, what: &str) -> Result<usize> {
        let n = self.usize()?;
        if let Some(e) = expected.filter(|&e| e != n) {
            bail!("{what}: {n} values in the snapshot, {e} here");
        }
        Ok(n)
    }
    /// Fills `out` from a slice of exactly its length.
    pub fn f64s_into(&mut self, out: &mut [f64], what: &str) -> Result<()> {
        self.len(Some(out.len()), what)?;
        for x in out {
            *x = self.f64()?;
        }
        Ok(())
    }
    pub fn f64s(&mut self) -> Result<Vec<f64>> {
        let n = self.len(None, "")?;
        ensure!(n <= self.data.len() / 8, "a slice longer than the snapshot");
        (0..n).map(|_| self.f64()).collect()
    }
    pub fn f32s_into(&mut self, out: &mut [f32], what: &str) -> Result<()> {
        self.len(Some(out.len()), what)?;
        for x in out {
            *x = f32::from_bits(u32::from_le_bytes(self.take(4)?.try_into()?));
        }
        Ok(())
    }
    pub fn bytes(&mut self) -> Result<&'a [u8]> {
        let n = self.usize()?;
        self.take(n)
    }
    pub fn rng(&mut self) -> Result<ChaCha8Rng> {
        let seed: [u8; 32] = self.take(32)?.try_into()?;
        let stream = self.u64()?;
        let pos = u128::from_le_bytes(self.take(16)?.try_into()?);
        let mut r = ChaCha8Rng::from_seed(seed);
        r.set_stream(stream);
        r.set_word_pos(pos);
        Ok(r)
    }
    /// Refuses bytes left over (a snapshot of another layout).
    pub fn finish(self) -> Result<()> {
        ensure!(
            self.at == self.data.len(),
            "the snapshot has {} bytes more than this build reads",
            self.data.len() - self.at
        );
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Vec<u8> {
        let mut w = StateWriter::new("t");
        w.u64(7);
        w.f64s(&[1.5, -0.0, f64::MIN_POSITIVE]);
        w.f32s(&[3.25]);
        w.rng(&ChaCha8Rng::seed_from_u64(4));
        w.into_bytes()
    }

    fn read(bytes: &[u8]) -> Result<(u64, Vec<f64>, [f32; 1], ChaCha8Rng)> {
        let mut r = StateReader::new(bytes, "t")?;
        let n = r.u64()?;
        let v = r.f64s()?;
        let mut f = [0.0f32];
        r.f32s_into(&mut f, "f")?;
        let rng = r.rng()?;
        r.finish()?;
        Ok((n, v, f, rng))
    }

    #[test]
    fn values_come_back_bit_for_bit_and_damage_is_an_error_not_a_panic() {
        let bytes = sample();
        let (n, v, f, rng) = read(&bytes).unwrap();
        assert_eq!((n, f), (7, [3.25]));
        assert_eq!(
            v.iter().map(|x| x.to_bits()).collect::<Vec<_>>(),
            [1.5f64, -0.0, f64::MIN_POSITIVE].map(f64::to_bits)
        );
        assert_eq!(rng, ChaCha8Rng::seed_from_u64(4));
        for cut in 0..bytes.len() {
            assert!(read(&bytes[..cut]).is_err(), "cut at {cut}");
        }
        let mut longer = bytes.clone();
        longer.push(0);
        assert!(read(&longer).is_err());
        for i in 0..bytes.len() {
            let mut b = bytes.clone();
            b[i] ^= 0x80;
            let _ = read(&b); // any result but a panic
        }
        assert!(StateReader::new(&bytes, "other").is_err());
    }
}
