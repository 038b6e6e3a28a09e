//! A cheap clock for timing short stretches of kernel work (one shadow
//! packet, a few hundred nanoseconds): two calls of `Instant::now` per
//! packet are a noticeable share of the shadow rays' own time, while the
//! processor's invariant time-stamp counter costs a few cycles.
//! Ticks become seconds by comparing with `Instant` over a longer stretch
//! ([`Calibration`]).

use std::sync::OnceLock;
use std::time::Instant;

/// Ticks of the cheapest steady clock: the time-stamp counter where the
/// CPU says it is invariant (constant rate, all cores), else nanoseconds
/// since the first call.
#[inline(always)]
pub fn ticks() -> u64 {
    #[cfg(target_arch = "x86_64")]
    if invariant_tsc() {
        // LFENCE first: without it the counter may be read before the work
        // in front of it has finished (out-of-order execution), and a
        // stretch of a few hundred cycles reads as almost nothing.
        // SAFETY: LFENCE (SSE2) and RDTSC exist on every x86_64 processor.
        return unsafe {
            std::arch::x86_64::_mm_lfence();
            std::arch::x86_64::_rdtsc()
        };
    }
    epoch().elapsed().as_nanos() as u64
}

fn epoch() -> &'static Instant {
    static EPOCH: OnceLock<Instant> = OnceLock::new();
    EPOCH.get_or_init(Instant::now)
}

#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn invariant_tsc() -> bool {
    static INVARIANT: OnceLock<bool> = OnceLock::new();
    *INVARIANT.get_or_init(|| {
        // CPUID 0x8000_0007, EDX bit 8: the TSC runs at a constant rate in
        // every power state.
        let max = std::arch::x86_64::__cpuid(0x8000_0000).eax;
        max >= 0x8000_0007 && std::arch::x86_64::__cpuid(0x8000_0007).edx & (1 << 8) != 0
    })
}

/// Converts ticks to seconds: started before the work, finished after it.
pub struct Calibration {
    instant: Instant,
    ticks: u64,
}

impl Calibration {
    pub fn start() -> Calibration {
        Calibration {
            instant: Instant::now(),
            ticks: ticks(),
        }
    }

    /// Seconds per tick over the stretch since `start` (0 when no tick
    /// passed).
    pub fn seconds_per_tick(&self) -> f64 {
        let dt = ticks().saturating_sub(self.ticks);
        let secs = self.instant.elapsed().as_secs_f64();
        if dt == 0 {
            0.0
        } else {
            secs / dt as f64
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ticks_advance_and_calibrate_to_a_positive_rate() {
        let calibration = Calibration::start();
        let a = ticks();
        // Work the clock can see, whatever its resolution.
        let until = Instant::now() + std::time::Duration::from_millis(2);
        while Instant::now() < until {
            std::hint::spin_loop();
        }
        let b = ticks();
        assert!(b > a, "the clock did not advance: {a} then {b}");
        let rate = calibration.seconds_per_tick();
        assert!(rate.is_finite() && rate > 0.0, "seconds per tick {rate}");
        // The stretch measured in ticks is at least the 2 ms waited.
        assert!(
            (b - a) as f64 * rate >= 0.002 * 0.5,
            "{} ticks at {rate} s",
            b - a
        );
    }
}
