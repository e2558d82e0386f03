//! The memory budget: every size read from a file or an argument is checked against what it
//! would allocate before anything is allocated, so a hostile or mistyped size ends in a clear
//! error instead of an allocation abort or a fill that looks like a hang.
//!
//! The limit is `--max-memory-gb` (a global option), by default 3/4 of the machine's physical
//! memory (`MemTotal` of /proc/meminfo; 8 GiB where that cannot be read).

use std::sync::atomic::{AtomicU64, Ordering};

/// The limit in bytes; 0 = not set yet (the machine's default applies).
static LIMIT_BYTES: AtomicU64 = AtomicU64::new(0);

const GIB: f64 = 1024.0 * 1024.0 * 1024.0;

/// A size that would allocate more than the budget.
#[derive(Debug, thiserror::Error)]
#[error(
    "{what} would need about {need:.1} GiB of memory, more than the limit of {limit:.1} GiB \
     ({fix}; or raise --max-memory-gb)"
)]
pub struct OverBudget {
    what: String,
    need: f64,
    limit: f64,
    fix: String,
}

/// 3/4 of the physical memory, bytes.
fn machine_default() -> u64 {
    let total_kib = std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|t| {
            t.lines()
                .find_map(|l| l.strip_prefix("MemTotal:"))
                .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
        })
        .unwrap_or(8 * 1024 * 1024);
    total_kib.saturating_mul(1024) / 4 * 3
}

/// Sets the limit from `--max-memory-gb` (must be positive and finite).
pub fn set_limit_gb(gb: f64) -> Result<(), String> {
    if !(gb.is_finite() && gb > 0.0) {
        return Err(format!(
            "--max-memory-gb {gb}: it must be a positive number of GiB"
        ));
    }
    LIMIT_BYTES.store((gb * GIB).max(1.0) as u64, Ordering::Relaxed);
    Ok(())
}

/// The limit in bytes.
pub fn limit_bytes() -> u64 {
    match LIMIT_BYTES.load(Ordering::Relaxed) {
        0 => machine_default(),
        n => n,
    }
}

/// Checks that `count` items of `bytes_each` fit the budget. `what` names the size (e.g.
/// "--samples 1000000000"), `fix` says how to ask for less.
pub fn check(what: &str, count: u128, bytes_each: u128, fix: &str) -> Result<(), OverBudget> {
    let need = count.saturating_mul(bytes_each);
    let limit = limit_bytes();
    if need > u128::from(limit) {
        return Err(OverBudget {
            what: what.to_string(),
            need: need as f64 / GIB,
            limit: limit as f64 / GIB,
            fix: fix.to_string(),
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_over_the_limit_are_refused_with_the_figures() {
        let limit = limit_bytes() as u128;
        assert!(check("x", limit / 8, 8, "ask less").is_ok());
        let e = check("--samples 9", limit, 2, "ask less")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("--samples 9") && e.contains("ask less") && e.contains("GiB"),
            "{e}"
        );
        // Overflowing products are over any limit, not wrapped around.
        assert!(check("y", u128::MAX, 3, "").is_err());
    }

    #[test]
    fn the_default_is_a_share_of_the_machine() {
        let d = machine_default();
        assert!(d > 100 * 1024 * 1024, "{d}");
    }
}
