//! Error-against-time measurements: one row per (configuration, samples per pixel), and the
//! log–log slope that Monte Carlo theory puts near −0.5 for error against time.

use serde::Serialize;

/// One render measured against the reference.
#[derive(Clone, Debug, Serialize)]
pub struct Measurement {
    /// The configuration's label (e.g. "2 threads").
    pub config: String,
    pub spp: u32,
    pub seconds: f64,
    pub rmse: f64,
    pub rel_mse: f64,
    pub mean_flip: f64,
    /// RMSE and relMSE of the linear f32 image against a linear reference, where a report
    /// has both: without the 8-bit quantisation, which adds an error floor no sampling lowers.
    pub rmse_linear: Option<f64>,
    pub rel_mse_linear: Option<f64>,
}

/// Least-squares slope of ln y against ln x; None with fewer than two usable points or no
/// spread in x. Non-positive values are skipped (a logarithm needs them positive).
pub fn log_log_slope(points: &[(f64, f64)]) -> Option<f64> {
    let logs: Vec<(f64, f64)> = points
        .iter()
        .filter(|(x, y)| *x > 0.0 && *y > 0.0 && x.is_finite() && y.is_finite())
        .map(|(x, y)| (x.ln(), y.ln()))
        .collect();
    if logs.len() < 2 {
        return None;
    }
    let n = logs.len() as f64;
    let mean_x = logs.iter().map(|p| p.0).sum::<f64>() / n;
    let mean_y = logs.iter().map(|p| p.1).sum::<f64>() / n;
    let sxx: f64 = logs.iter().map(|p| (p.0 - mean_x).powi(2)).sum();
    let sxy: f64 = logs.iter().map(|p| (p.0 - mean_x) * (p.1 - mean_y)).sum();
    (sxx > 0.0).then(|| sxy / sxx)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn slope_of_a_power_law_is_its_exponent() {
        let points: Vec<(f64, f64)> = (1..6)
            .map(|i| (i as f64, 3.0 / (i as f64).sqrt()))
            .collect();
        assert!((log_log_slope(&points).unwrap() + 0.5).abs() < 1e-12);
        assert_eq!(log_log_slope(&[(1.0, 1.0)]), None);
        assert_eq!(log_log_slope(&[(2.0, 1.0), (2.0, 3.0)]), None);
        assert!(log_log_slope(&[(1.0, 0.0), (2.0, 1.0), (4.0, 2.0)]).is_some());
    }
}
