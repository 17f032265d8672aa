//! Non-linear compliance: the lung's pressure–volume curve as a table, which the compliance
//! driver reads each frame's pressure from instead of ΔP = ΔV / C.
//!
//! A row is `[pressure_pa, volume_ml]`: the distending (transpulmonary) pressure change from
//! the scanned state, Pa, positive inflating, and the lung volume change it gives, mL. The
//! surface pressure applied is its negative (positive surface pressure pushes inward, see
//! [`crate::model::SurfacePressure`]). Rows rise strictly in both columns (volume rises with
//! pressure), pass through the scanned state `[0, 0]` and are interpolated piecewise-linearly;
//! a volume outside the table's range is refused, never extrapolated. A table of two rows
//! `[0, 0]`, `[P, C·P]` is the constant compliance C.

use serde::{Deserialize, Serialize};

use crate::{Error, Result};

/// Fewest rows of a pressure–volume table (two make a line).
pub const MIN_PRESSURE_VOLUME_ROWS: usize = 2;
/// Most rows of a pressure–volume table (a measured curve has tens).
pub const MAX_PRESSURE_VOLUME_ROWS: usize = 1000;
/// Largest |pressure| in a table, Pa (10 kPa ≈ 100 cmH₂O, three times total lung capacity's).
pub const MAX_TABLE_PRESSURE_PA: f64 = 10_000.0;
/// Largest |volume change| in a table, mL (beyond any lung's vital capacity).
pub const MAX_TABLE_VOLUME_ML: f64 = 10_000.0;

/// A pressure–volume table: rows `[distending pressure change Pa, volume change mL]` (see the
/// module doc).
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(transparent)]
pub struct PressureVolumeTable(pub Vec<[f64; 2]>);

impl<'de> Deserialize<'de> for PressureVolumeTable {
    /// Rows of any length are read, so a row that is not a pair is refused naming the key,
    /// the row and its values (serde's own message names neither).
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        let rows = Vec::<Vec<f64>>::deserialize(d)?;
        rows.into_iter()
            .enumerate()
            .map(|(i, row)| match row[..] {
                [p, v] => Ok([p, v]),
                _ => Err(serde::de::Error::custom(format!(
                    "pressure_volume row {} {row:?} has {} value(s): each row is [pressure Pa, \
                     volume mL]",
                    i + 1,
                    row.len()
                ))),
            })
            .collect::<std::result::Result<_, _>>()
            .map(PressureVolumeTable)
    }
}

impl PressureVolumeTable {
    /// Why the table cannot drive a lung, naming the row (1-based) and its values, if it
    /// cannot.
    pub fn problem(&self) -> Option<String> {
        let rows = &self.0;
        if rows.len() < MIN_PRESSURE_VOLUME_ROWS {
            return Some(format!(
                "{} row(s): a pressure–volume table needs at least {MIN_PRESSURE_VOLUME_ROWS} \
                 rows [pressure Pa, volume mL]",
                rows.len()
            ));
        }
        if rows.len() > MAX_PRESSURE_VOLUME_ROWS {
            return Some(format!(
                "{} rows is beyond the {MAX_PRESSURE_VOLUME_ROWS}-row maximum",
                rows.len()
            ));
        }
        for (i, &[p, v]) in rows.iter().enumerate() {
            let row = i + 1;
            if !(p.is_finite() && v.is_finite()) {
                return Some(format!(
                    "row {row} [{p}, {v}]: pressure and volume must be finite numbers"
                ));
            }
            if p.abs() > MAX_TABLE_PRESSURE_PA {
                return Some(format!(
                    "row {row} [{p}, {v}]: pressure {p} Pa is beyond ±{MAX_TABLE_PRESSURE_PA} Pa \
                     (a unit mistake? the table is in Pa, not cmH₂O·10⁻²)"
                ));
            }
            if v.abs() > MAX_TABLE_VOLUME_ML {
                return Some(format!(
                    "row {row} [{p}, {v}]: volume {v} mL is beyond ±{MAX_TABLE_VOLUME_ML} mL (a \
                     unit mistake? the table is in mL)"
                ));
            }
            if i > 0 {
                let [p0, v0] = rows[i - 1];
                if p <= p0 {
                    return Some(format!(
                        "row {row} [{p}, {v}]: pressure {p} Pa is not above row {i}'s {p0} Pa \
                         (rows go by rising pressure)"
                    ));
                }
                if v <= v0 {
                    return Some(format!(
                        "row {row} [{p}, {v}]: volume {v} mL is not above row {i}'s {v0} mL \
                         (volume must rise with pressure: a compliance that is not positive \
                         has no equilibrium to drive to)"
                    ));
                }
            }
        }
        let (lo, hi) = self.volume_range_ml();
        if !(lo <= 0.0 && 0.0 <= hi) {
            return Some(format!(
                "volumes {lo}…{hi} mL do not include 0: the table must pass through the scanned \
                 state [0, 0]"
            ));
        }
        let p0 = self.interpolate_pressure(0.0);
        let span = rows[rows.len() - 1][0] - rows[0][0];
        if p0.abs() > 1e-9 * span {
            return Some(format!(
                "at volume 0 mL the table gives {p0} Pa: the scanned state is at rest, so the \
                 table must pass through [0, 0]"
            ));
        }
        None
    }

    /// [`Self::problem`] as an error naming the setting.
    pub fn validate(&self) -> Result<()> {
        match self.problem() {
            Some(reason) => Err(Error::Config {
                settings: "motion settings",
                file: None,
                key: Some("motion.driver.pressure_volume".into()),
                reason,
            }),
            None => Ok(()),
        }
    }

    /// Lowest and highest volume change of the table, mL.
    pub fn volume_range_ml(&self) -> (f64, f64) {
        let rows = &self.0;
        (rows[0][1], rows[rows.len() - 1][1])
    }

    /// Distending pressure change that gives volume change `volume_ml`, Pa (piecewise-linear
    /// in the table); refused outside the table's volumes.
    pub fn pressure_pa(&self, volume_ml: f64) -> Result<f64> {
        let (lo, hi) = self.volume_range_ml();
        if !(volume_ml.is_finite() && lo <= volume_ml && volume_ml <= hi) {
            return Err(Error::Config {
                settings: "motion settings",
                file: None,
                key: Some("motion.driver.pressure_volume".into()),
                reason: format!(
                    "the trace asks for {volume_ml} mL, outside the table's {lo}…{hi} mL: the \
                     table is not extrapolated, extend it to the trace's volumes"
                ),
            });
        }
        Ok(self.interpolate_pressure(volume_ml))
    }

    /// Compliance of the table at the scanned state, mL/Pa: the slope of the segment above
    /// volume 0 (below it when 0 is the last row). Seeds the driver and is reported.
    pub fn compliance_at_rest_ml_per_pa(&self) -> f64 {
        let rows = &self.0;
        let k = rows
            .iter()
            .position(|r| r[1] > 0.0)
            .unwrap_or(rows.len() - 1)
            .max(1);
        let ([p0, v0], [p1, v1]) = (rows[k - 1], rows[k]);
        (v1 - v0) / (p1 - p0)
    }

    /// Piecewise-linear pressure at `volume_ml`, clamped to the end rows.
    fn interpolate_pressure(&self, volume_ml: f64) -> f64 {
        let rows = &self.0;
        let k = rows
            .iter()
            .position(|r| r[1] >= volume_ml)
            .unwrap_or(rows.len() - 1)
            .max(1);
        let ([p0, v0], [p1, v1]) = (rows[k - 1], rows[k]);
        let t = ((volume_ml - v0) / (v1 - v0)).clamp(0.0, 1.0);
        p0 + t * (p1 - p0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn table(rows: &[[f64; 2]]) -> PressureVolumeTable {
        PressureVolumeTable(rows.to_vec())
    }

    #[test]
    fn the_table_interpolates_pressure_piecewise_linearly() {
        let t = table(&[[-100.0, -150.0], [0.0, 0.0], [200.0, 500.0], [600.0, 900.0]]);
        assert!(t.problem().is_none());
        assert_eq!(t.pressure_pa(0.0).unwrap(), 0.0);
        assert!((t.pressure_pa(250.0).unwrap() - 100.0).abs() < 1e-12);
        assert!((t.pressure_pa(700.0).unwrap() - 400.0).abs() < 1e-12);
        assert!((t.pressure_pa(-75.0).unwrap() + 50.0).abs() < 1e-12);
        assert_eq!(t.pressure_pa(900.0).unwrap(), 600.0);
        assert!((t.compliance_at_rest_ml_per_pa() - 2.5).abs() < 1e-12);
        // A constant compliance is a two-row table.
        let c = table(&[[0.0, 0.0], [1000.0, 2000.0]]);
        assert!((c.pressure_pa(700.0).unwrap() - 350.0).abs() < 1e-12);
        assert_eq!(c.compliance_at_rest_ml_per_pa(), 2.0);
    }

    #[test]
    fn a_volume_beyond_the_table_is_refused_not_extrapolated() {
        let t = table(&[[0.0, 0.0], [200.0, 500.0]]);
        let e = t.pressure_pa(501.0).unwrap_err().to_string();
        assert!(
            e.contains("motion.driver.pressure_volume") && e.contains("501 mL"),
            "{e}"
        );
        assert!(t.pressure_pa(-1.0).is_err());
        assert!(t.pressure_pa(f64::NAN).is_err());
    }

    #[test]
    fn tables_that_cannot_drive_a_lung_are_refused_with_the_row_and_the_reason() {
        let why = |rows: &[[f64; 2]]| table(rows).problem().expect("refused");
        let few = why(&[[0.0, 0.0]]);
        assert!(
            few.contains("1 row(s)") && few.contains("at least 2"),
            "{few}"
        );
        assert!(why(&[]).contains("0 row(s)"));
        let many: Vec<[f64; 2]> = (0..1001).map(|i| [i as f64, i as f64]).collect();
        assert!(why(&many).contains("1001 rows"));
        let nan = why(&[[0.0, 0.0], [f64::NAN, 10.0]]);
        assert!(
            nan.contains("row 2 [NaN, 10]") && nan.contains("finite"),
            "{nan}"
        );
        let inf = why(&[[0.0, 0.0], [10.0, f64::INFINITY]]);
        assert!(inf.contains("row 2") && inf.contains("finite"), "{inf}");
        let falling = why(&[[0.0, 0.0], [100.0, 300.0], [200.0, 250.0]]);
        assert!(
            falling.contains("row 3 [200, 250]")
                && falling.contains("250 mL is not above row 2's 300 mL")
                && falling.contains("volume must rise with pressure"),
            "{falling}"
        );
        let flat = why(&[[0.0, 0.0], [100.0, 300.0], [200.0, 300.0]]);
        assert!(flat.contains("volume must rise"), "{flat}");
        let unsorted = why(&[[0.0, 0.0], [200.0, 300.0], [100.0, 400.0]]);
        assert!(
            unsorted.contains("row 3") && unsorted.contains("100 Pa is not above row 2's 200 Pa"),
            "{unsorted}"
        );
        let off = why(&[[10.0, 0.0], [100.0, 300.0]]);
        assert!(
            off.contains("gives 10 Pa") && off.contains("[0, 0]"),
            "{off}"
        );
        let above = why(&[[10.0, 5.0], [100.0, 300.0]]);
        assert!(above.contains("do not include 0"), "{above}");
        let kpa = why(&[[0.0, 0.0], [20_000.0, 300.0]]);
        assert!(kpa.contains("20000 Pa") && kpa.contains("±10000"), "{kpa}");
        let litres = why(&[[0.0, 0.0], [200.0, 20_000.0]]);
        assert!(litres.contains("20000 mL"), "{litres}");
        let e = table(&[[0.0, 0.0]]).validate().unwrap_err().to_string();
        assert!(e.contains("motion.driver.pressure_volume"), "{e}");
    }
}
