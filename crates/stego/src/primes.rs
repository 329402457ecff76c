//! Primality (deterministic Miller–Rabin for u64) and random primes from the OS CSPRNG.

use ngp::error::{Error, Result};

/// The range the paper draws its primes from.
pub const PRIME_RANGE: (u64, u64) = (10_000_000, 10_000_000_000);

/// Primes in [1e7, 1e10] (the paper's count, P(1e10) − P(1e7)).
pub const PRIMES_IN_RANGE: f64 = 454_387_932.0;

fn mul_mod(a: u64, b: u64, m: u64) -> u64 {
    ((a as u128 * b as u128) % m as u128) as u64
}

fn pow_mod(mut b: u64, mut e: u64, m: u64) -> u64 {
    let mut r = 1u64 % m;
    b %= m;
    while e > 0 {
        if e & 1 == 1 {
            r = mul_mod(r, b, m);
        }
        b = mul_mod(b, b, m);
        e >>= 1;
    }
    r
}

/// Deterministic for every u64: the first 12 primes as bases are a proven witness set
/// below 3.3·10^24.
pub fn is_prime(n: u64) -> bool {
    const BASES: [u64; 12] = [2, 3, 5, 7, 11, 13, 17, 19, 23, 29, 31, 37];
    if n < 2 {
        return false;
    }
    for &p in &BASES {
        if n.is_multiple_of(p) {
            return n == p;
        }
    }
    let s = (n - 1).trailing_zeros();
    let d = (n - 1) >> s;
    'bases: for &a in &BASES {
        let mut x = pow_mod(a, d, n);
        if x == 1 || x == n - 1 {
            continue;
        }
        for _ in 1..s {
            x = mul_mod(x, x, n);
            if x == n - 1 {
                continue 'bases;
            }
        }
        return false;
    }
    true
}

/// Uniform over the primes of `[lo, hi]`: uniform integers are drawn until one is prime
/// (taking the next prime after a random point would favour primes after long gaps).
pub fn random_prime_with(
    lo: u64,
    hi: u64,
    mut next_u64: impl FnMut() -> Result<u64>,
) -> Result<u64> {
    let span = hi - lo + 1;
    // Rejection sampling removes the modulo bias.
    let zone = u64::MAX - (u64::MAX % span);
    loop {
        let r = next_u64()?;
        if r >= zone {
            continue;
        }
        let n = lo + r % span;
        if is_prime(n) {
            return Ok(n);
        }
    }
}

/// A u64 from the operating system's CSPRNG.
pub fn os_u64() -> Result<u64> {
    getrandom::u64().map_err(|e| Error::Other(format!("OS random number generator: {e}")))
}

/// `m` triples of distinct random primes in the paper's range, from the OS CSPRNG.
pub fn random_prime_triples(
    m: usize,
    mut next_u64: impl FnMut() -> Result<u64>,
) -> Result<Vec<[u64; 3]>> {
    let mut seen = std::collections::HashSet::new();
    let mut out = Vec::with_capacity(m);
    for _ in 0..m {
        let mut t = [0u64; 3];
        for k in &mut t {
            loop {
                let p = random_prime_with(PRIME_RANGE.0, PRIME_RANGE.1, &mut next_u64)?;
                if seen.insert(p) {
                    *k = p;
                    break;
                }
            }
        }
        out.push(t);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn trial_division(n: u64) -> bool {
        if n < 2 {
            return false;
        }
        let mut d = 2u64;
        while d * d <= n {
            if n.is_multiple_of(d) {
                return false;
            }
            d += 1;
        }
        true
    }

    #[test]
    fn miller_rabin_agrees_with_trial_division() {
        for n in 0..20_000u64 {
            assert_eq!(is_prime(n), trial_division(n), "{n}");
        }
        for n in 10_000_000_000u64..10_000_002_000 {
            assert_eq!(is_prime(n), trial_division(n), "{n}");
        }
        // Strong pseudoprimes to several small bases, and the largest u64 prime.
        assert!(!is_prime(3_215_031_751));
        assert!(!is_prime(3_825_123_056_546_413_051));
        assert!(is_prime(18_446_744_073_709_551_557));
        // The reference constants π2, π3 are prime; π1 = 1 is not.
        assert!(is_prime(2_654_435_761) && is_prime(805_459_861) && !is_prime(1));
    }
}
