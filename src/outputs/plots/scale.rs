//! Axis numbers of the plots: data ranges, round tick steps, tick labels and the round
//! values a colour bar ends on.

/// Smallest and largest of `values`.
pub(super) fn min_max(values: impl Iterator<Item = f64>) -> (f64, f64) {
    values.fold((f64::MAX, f64::MIN), |(lo, hi), v| (lo.min(v), hi.max(v)))
}

/// Opens a flat range around its value so the axis has a span.
pub(super) fn widen_if_flat(lo: f64, hi: f64, half_span: f64) -> (f64, f64) {
    if hi - lo > 1e-9 * (lo.abs() + hi.abs()).max(1.0) {
        (lo, hi)
    } else {
        (lo - half_span, hi + half_span)
    }
}

/// A 1, 2 or 5 × 10ⁿ step giving about `target` intervals over `range`.
pub(super) fn nice_step(range: f64, target: usize) -> f64 {
    let raw = (range / target as f64).max(f64::MIN_POSITIVE);
    let magnitude = 10f64.powf(raw.log10().floor());
    let f = raw / magnitude;
    let nice = if f <= 1.0 {
        1.0
    } else if f <= 2.0 {
        2.0
    } else if f <= 5.0 {
        5.0
    } else {
        10.0
    };
    nice * magnitude
}

/// Multiples of `step` within [lo, hi].
pub(super) fn ticks(lo: f64, hi: f64, step: f64) -> impl Iterator<Item = f64> {
    let first = (lo / step - 1e-9).ceil() as i64;
    let last = (hi / step + 1e-9).floor() as i64;
    (first..=last).map(move |k| k as f64 * step)
}

/// A tick value with as many decimals as its step needs.
pub(super) fn format_tick(v: f64, step: f64) -> String {
    let decimals = (-step.log10().floor()).max(0.0) as usize;
    let v = if v.abs() < 0.5 * step { 0.0 } else { v };
    format!("{v:.decimals$}")
}

/// A value with at most two significant decimals, no trailing zeros.
pub(super) fn format_value(v: f64) -> String {
    let s = format!("{v:.2}");
    s.trim_end_matches('0').trim_end_matches('.').to_string()
}

/// Round numbers a colour bar may end on, per decade.
const ROUND_STEPS: [f64; 10] = [1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0];

/// The smallest round number ≥ `v` (1 for nothing to show).
pub(super) fn round_up(v: f64) -> f64 {
    if v.is_nan() || v <= 0.0 {
        return 1.0;
    }
    let decade = 10f64.powf(v.log10().floor());
    ROUND_STEPS
        .iter()
        .map(|s| s * decade)
        .find(|&r| r >= v * (1.0 - 1e-9))
        .unwrap_or(10.0 * decade)
}

/// The largest round number ≤ `v`.
pub(super) fn round_down(v: f64) -> f64 {
    let decade = 10f64.powf(v.log10().floor());
    ROUND_STEPS
        .iter()
        .rev()
        .map(|s| s * decade)
        .find(|&r| r <= v * (1.0 + 1e-9))
        .unwrap_or(decade)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_numbers_bracket_the_value() {
        assert_eq!(round_up(10.1), 15.0);
        assert_eq!(round_up(0.37), 0.4);
        assert_eq!(round_up(20.0), 20.0);
        assert_eq!(round_down(17.0), 15.0);
        assert_eq!(round_down(0.9), 0.8);
        assert_eq!(nice_step(100.0, 5), 20.0);
        assert_eq!(nice_step(7.0, 8), 1.0);
        assert_eq!(
            ticks(-12.0, 41.0, 10.0).collect::<Vec<_>>(),
            [-10.0, 0.0, 10.0, 20.0, 30.0, 40.0]
        );
        assert_eq!(format_tick(0.5, 0.5), "0.5");
        assert_eq!(format_tick(-1e-17, 0.1), "0.0");
        assert_eq!(format_value(2.5), "2.5");
        assert_eq!(format_value(10.0), "10");
    }
}
