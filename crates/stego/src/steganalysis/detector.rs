//! A combined detector: logistic regression on standardised features, and ROC AUC.
//!
//! Logistic regression because the population is small (tens of models) and the features
//! are few and roughly monotone in "how much of the table was trained": a linear score is
//! what such data supports, and its weights say which statistic carries the evidence.

use ngp::error::{Error, Result};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::path::Path;

/// One feature of a fitted detector: how to standardise it and its weight.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FeatureWeight {
    pub name: String,
    /// Training mean: also the value a missing feature is given.
    pub mean: f64,
    /// Training standard deviation (population), > 0.
    pub std: f64,
    pub weight: f64,
}

/// `P(stego | features) = σ(bias + Σ weight·clamp((x − mean)/std, ±Z_CLAMP))`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Detector {
    /// What the detector was fitted on, in words (models, sizes, how many of each class).
    pub fitted_on: String,
    pub classifier: String,
    /// L2 penalty on the weights (not the bias), in standardised units.
    pub l2: f64,
    pub bias: f64,
    pub features: Vec<FeatureWeight>,
}

/// Standardised values are clamped to this many standard deviations when scoring: a model
/// far outside the training population (another table size, a real capture) should not let
/// one extreme feature decide alone.
pub const Z_CLAMP: f64 = 6.0;

fn sigmoid(t: f64) -> f64 {
    if t >= 0.0 {
        1.0 / (1.0 + (-t).exp())
    } else {
        let e = t.exp();
        e / (1.0 + e)
    }
}

/// Aligns feature lists by name: the union of names (in order of first appearance) and one
/// row per sample, NaN where a sample lacks a name (fit treats NaN as missing).
pub fn feature_matrix(samples: &[Vec<(String, f64)>]) -> (Vec<String>, Vec<Vec<f64>>) {
    let mut names: Vec<String> = Vec::new();
    let mut col: HashMap<String, usize> = HashMap::new();
    for s in samples {
        for (n, _) in s {
            if !col.contains_key(n) {
                col.insert(n.clone(), names.len());
                names.push(n.clone());
            }
        }
    }
    let rows = samples
        .iter()
        .map(|s| {
            let mut r = vec![f64::NAN; names.len()];
            for (n, v) in s {
                r[col[n]] = *v;
            }
            r
        })
        .collect();
    (names, rows)
}

/// Solves `a·x = b` for a symmetric positive definite `a` (row-major n×n) by Cholesky.
fn cholesky_solve(a: &[f64], b: &[f64], n: usize) -> Option<Vec<f64>> {
    let mut l = vec![0.0; n * n];
    for i in 0..n {
        for j in 0..=i {
            let mut s = a[i * n + j];
            for k in 0..j {
                s -= l[i * n + k] * l[j * n + k];
            }
            if i == j {
                if s <= 0.0 || !s.is_finite() {
                    return None;
                }
                l[i * n + i] = s.sqrt();
            } else {
                l[i * n + j] = s / l[j * n + j];
            }
        }
    }
    let mut y = vec![0.0; n];
    for i in 0..n {
        let s: f64 = (0..i).map(|k| l[i * n + k] * y[k]).sum();
        y[i] = (b[i] - s) / l[i * n + i];
    }
    let mut x = vec![0.0; n];
    for i in (0..n).rev() {
        let s: f64 = (i + 1..n).map(|k| l[k * n + i] * x[k]).sum();
        x[i] = (y[i] - s) / l[i * n + i];
    }
    Some(x)
}

impl Detector {
    /// Default L2 penalty: with tens of models and tens of features the classes are
    /// usually separable, where an unpenalised fit diverges; 1 (in standardised units, on
    /// the summed log-likelihood) keeps the weights finite and near what one feature alone
    /// would give.
    pub const DEFAULT_L2: f64 = 1.0;

    /// [`Detector::fit_with`] at [`Detector::DEFAULT_L2`].
    pub fn fit(names: &[String], rows: &[Vec<f64>], labels: &[bool]) -> Result<Detector> {
        Self::fit_with(names, rows, labels, Self::DEFAULT_L2)
    }

    /// Fits `P(stego)` by Newton's method (IRLS) on the penalised log-likelihood:
    /// deterministic, and exact to 1e-10 in the weights. `rows[i][j]` is feature `names[j]`
    /// of model `i`; NaN or ±∞ means missing and is replaced by the feature's mean. Features
    /// missing everywhere or constant are left out. `labels[i]`: model `i` is stego.
    pub fn fit_with(
        names: &[String],
        rows: &[Vec<f64>],
        labels: &[bool],
        l2: f64,
    ) -> Result<Detector> {
        check_fit_inputs(names, rows, labels, l2)?;
        let (mut feats, cols) = standardisation(names, rows);
        let problem = Logistic {
            x: design_matrix(rows, &feats, &cols),
            y: labels.iter().map(|&b| if b { 1.0 } else { 0.0 }).collect(),
            p: feats.len() + 1,
            l2,
        };
        let beta = problem.newton()?;
        for (f, b) in feats.iter_mut().zip(&beta[1..]) {
            f.weight = *b;
        }
        Ok(Detector {
            fitted_on: String::new(),
            classifier: format!(
                "logistic regression on standardised features (Newton/IRLS, L2 {l2} on the weights, z clamped to ±{Z_CLAMP} when scoring)"
            ),
            l2,
            bias: beta[0],
            features: feats,
        })
    }

    /// Probability in [0, 1] that the model with these features is stego. Features the
    /// detector does not know are ignored; features it knows but the model lacks (or NaN)
    /// take the training mean.
    pub fn score(&self, features: &[(String, f64)]) -> f64 {
        let given: HashMap<&str, f64> = features.iter().map(|(n, v)| (n.as_str(), *v)).collect();
        let t: f64 = self.bias
            + self
                .features
                .iter()
                .map(|f| match given.get(f.name.as_str()) {
                    Some(v) if v.is_finite() => {
                        f.weight * ((v - f.mean) / f.std).clamp(-Z_CLAMP, Z_CLAMP)
                    }
                    _ => 0.0,
                })
                .sum::<f64>();
        sigmoid(t)
    }

    /// Parses and checks a detector's JSON; `what` names its origin in errors.
    fn from_json(s: &str, what: &Path) -> Result<Detector> {
        let d: Detector = serde_json::from_str(s)
            .map_err(|e| Error::format(what, format!("not a detector file: {e}")))?;
        let ok = d.bias.is_finite()
            && d.features.iter().all(|f| {
                f.mean.is_finite() && f.weight.is_finite() && f.std.is_finite() && f.std > 0.0
            });
        if !ok {
            return Err(Error::format(
                what,
                "detector has a non-finite number or a standard deviation ≤ 0",
            ));
        }
        Ok(d)
    }

    pub fn load(path: &Path) -> Result<Detector> {
        let s = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        Self::from_json(&s, path)
    }

    /// Writes the detector as pretty JSON, atomically (temporary file, then rename).
    pub fn save(&self, path: &Path) -> Result<()> {
        let mut s = serde_json::to_string_pretty(self)
            .map_err(|e| Error::format(path, format!("cannot encode detector: {e}")))?;
        s.push('\n');
        ngp::util::write_atomic(path, s.as_bytes())
    }

    /// The detector shipped in `assets/detector.json`.
    pub fn embedded() -> Result<Detector> {
        Self::from_json(
            include_str!("../../../../assets/detector.json"),
            Path::new("assets/detector.json (built in)"),
        )
    }
}

/// An error of [`Detector::fit_with`].
fn fit_error(m: String) -> Error {
    Error::Other(format!("detector fit: {m}"))
}

/// [`Detector::fit_with`]'s checks of its arguments' shapes, classes and penalty.
fn check_fit_inputs(names: &[String], rows: &[Vec<f64>], labels: &[bool], l2: f64) -> Result<()> {
    if rows.len() != labels.len() {
        return Err(fit_error(format!(
            "{} rows but {} labels",
            rows.len(),
            labels.len()
        )));
    }
    if let Some((i, r)) = rows
        .iter()
        .enumerate()
        .find(|(_, r)| r.len() != names.len())
    {
        return Err(fit_error(format!(
            "row {i} has {} values for {} names",
            r.len(),
            names.len()
        )));
    }
    let n_pos = labels.iter().filter(|&&y| y).count();
    if n_pos == 0 || n_pos == labels.len() {
        return Err(fit_error(format!(
            "needs plain and stego models, got {n_pos} stego of {}",
            labels.len()
        )));
    }
    if !(l2 > 0.0 && l2.is_finite()) {
        return Err(fit_error(format!(
            "the L2 penalty must be positive, got {l2}"
        )));
    }
    Ok(())
}

/// Standardisation over the values present: each usable feature's mean and standard
/// deviation (its weight 0 for now), and its column in `rows`. Features missing everywhere
/// or constant are left out.
fn standardisation(names: &[String], rows: &[Vec<f64>]) -> (Vec<FeatureWeight>, Vec<usize>) {
    let mut feats: Vec<FeatureWeight> = Vec::new();
    let mut cols: Vec<usize> = Vec::new();
    for (j, name) in names.iter().enumerate() {
        let vals: Vec<f64> = rows
            .iter()
            .map(|r| r[j])
            .filter(|v| v.is_finite())
            .collect();
        if vals.is_empty() {
            continue;
        }
        let mean = vals.iter().sum::<f64>() / vals.len() as f64;
        let var = vals.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / vals.len() as f64;
        let std = var.sqrt();
        if std == 0.0 || std <= 1e-12 * mean.abs() {
            continue;
        }
        feats.push(FeatureWeight {
            name: name.clone(),
            mean,
            std,
            weight: 0.0,
        });
        cols.push(j);
    }
    (feats, cols)
}

/// One row a model: 1 (the bias's input), then its standardised features (0, the mean,
/// where one is missing).
fn design_matrix(rows: &[Vec<f64>], feats: &[FeatureWeight], cols: &[usize]) -> Vec<Vec<f64>> {
    let p = feats.len() + 1;
    rows.iter()
        .map(|r| {
            let mut z = Vec::with_capacity(p);
            z.push(1.0);
            for (f, &j) in feats.iter().zip(cols) {
                let v = r[j];
                z.push(if v.is_finite() {
                    (v - f.mean) / f.std
                } else {
                    0.0
                });
            }
            z
        })
        .collect()
}

/// The penalised logistic regression [`Detector::fit_with`] solves: design rows `x` of
/// `p` values (the bias's input first), labels `y` (1 = stego), and the L2 penalty `l2` on
/// all coefficients but the bias.
struct Logistic {
    x: Vec<Vec<f64>>,
    y: Vec<f64>,
    p: usize,
    l2: f64,
}

impl Logistic {
    /// The penalised negative log-likelihood at `beta`.
    fn objective(&self, beta: &[f64]) -> f64 {
        let mut nll = 0.0;
        for (xi, &yi) in self.x.iter().zip(&self.y) {
            let t: f64 = xi.iter().zip(beta).map(|(a, b)| a * b).sum();
            // log(1 + e^t) − y·t, stably.
            nll += t.max(0.0) + (-t.abs()).exp().ln_1p() - yi * t;
        }
        nll + 0.5 * self.l2 * beta[1..].iter().map(|b| b * b).sum::<f64>()
    }

    /// The objective's gradient and Hessian (row-major `p`×`p`) at `beta`.
    fn gradient_hessian(&self, beta: &[f64]) -> (Vec<f64>, Vec<f64>) {
        let p = self.p;
        let mut g = vec![0.0; p];
        let mut h = vec![0.0; p * p];
        for (xi, &yi) in self.x.iter().zip(&self.y) {
            let t: f64 = xi.iter().zip(beta).map(|(a, b)| a * b).sum();
            let s = sigmoid(t);
            let w = s * (1.0 - s);
            for a in 0..p {
                g[a] += (s - yi) * xi[a];
                for b in 0..=a {
                    h[a * p + b] += w * xi[a] * xi[b];
                }
            }
        }
        for a in 0..p {
            for b in 0..a {
                h[b * p + a] = h[a * p + b];
            }
            if a > 0 {
                g[a] += self.l2 * beta[a];
                h[a * p + a] += self.l2;
            } else {
                // The bias is unpenalised; a hair of curvature keeps the system
                // definite when every probability saturates.
                h[0] += 1e-9;
            }
        }
        (g, h)
    }

    /// Newton with step halving: `beta − t·step` for t = 1, 1/2, … until the objective
    /// (`obj` at `beta`) does not grow, which it must for some t as it is convex. The last
    /// point tried and its objective (above `obj` when 30 halvings found none).
    fn line_search(&self, beta: &[f64], step: &[f64], obj: f64) -> (Vec<f64>, f64) {
        let mut t = 1.0;
        let mut next = beta.to_vec();
        let mut next_obj = obj;
        for _ in 0..30 {
            for a in 0..self.p {
                next[a] = beta[a] - t * step[a];
            }
            next_obj = self.objective(&next);
            if next_obj <= obj {
                break;
            }
            t *= 0.5;
        }
        (next, next_obj)
    }

    /// The coefficients (bias first) minimising the objective, from zero: at most 100
    /// Newton steps, until one moves no coefficient by 1e-10 or fails to descend.
    fn newton(&self) -> Result<Vec<f64>> {
        let p = self.p;
        let mut beta = vec![0.0; p];
        let mut obj = self.objective(&beta);
        for _ in 0..100 {
            let (g, h) = self.gradient_hessian(&beta);
            let step = cholesky_solve(&h, &g, p)
                .ok_or_else(|| fit_error("the Newton system is singular".into()))?;
            let (next, next_obj) = self.line_search(&beta, &step, obj);
            let moved = (0..p)
                .map(|a| (next[a] - beta[a]).abs())
                .fold(0.0, f64::max);
            if next_obj > obj {
                break;
            }
            beta = next;
            obj = next_obj;
            if moved < 1e-10 {
                break;
            }
        }
        Ok(beta)
    }
}

/// Area under the ROC curve of scores where higher means "stego": the probability that a
/// random positive scores above a random negative, ties counting one half (the
/// Mann–Whitney U statistic over n_pos·n_neg). NaN when either side is empty.
pub fn roc_auc(scores_pos: &[f64], scores_neg: &[f64]) -> f64 {
    if scores_pos.is_empty() || scores_neg.is_empty() {
        return f64::NAN;
    }
    // Midranks over the pooled sample: U = R_pos − n_pos(n_pos+1)/2.
    let mut all: Vec<(f64, bool)> = scores_pos
        .iter()
        .map(|&s| (s, true))
        .chain(scores_neg.iter().map(|&s| (s, false)))
        .collect();
    all.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut rank_sum = 0.0;
    let mut i = 0;
    while i < all.len() {
        let mut j = i;
        while j + 1 < all.len() && all[j + 1].0 == all[i].0 {
            j += 1;
        }
        // Ranks i+1..=j+1 share their mean.
        let mid = (i + j + 2) as f64 / 2.0;
        rank_sum += mid * all[i..=j].iter().filter(|(_, p)| *p).count() as f64;
        i = j + 1;
    }
    let (np, nn) = (scores_pos.len() as f64, scores_neg.len() as f64);
    (rank_sum - np * (np + 1.0) / 2.0) / (np * nn)
}

/// How often chance alone gives an AUC of at least `auc` on `n_pos` positives and `n_neg`
/// negatives: the one-sided p-value of the Mann–Whitney test, exact (the null distribution
/// of U counted over all C(n_pos + n_neg, n_pos) orders). Tied scores make U a half-integer;
/// it is rounded down, which counts ties against the detector (a conservative p). NaN when
/// either side is empty or `auc` is NaN.
pub fn auc_p_value(auc: f64, n_pos: usize, n_neg: usize) -> f64 {
    if n_pos == 0 || n_neg == 0 || !auc.is_finite() {
        return f64::NAN;
    }
    let u_max = n_pos * n_neg;
    let u_obs = ((auc * u_max as f64) + 1e-9)
        .floor()
        .clamp(0.0, u_max as f64) as usize;
    // ways[j][u]: orders of i positives and j negatives with U = u, rebuilt for each i from
    // the last (the largest score is a positive, above all j negatives, or a negative).
    let mut ways: Vec<Vec<f64>> = (0..=n_neg).map(|_| vec![0.0; u_max + 1]).collect();
    for w in ways.iter_mut() {
        w[0] = 1.0;
    }
    for _ in 1..=n_pos {
        let mut next: Vec<Vec<f64>> = (0..=n_neg).map(|_| vec![0.0; u_max + 1]).collect();
        for j in 0..=n_neg {
            for u in 0..=u_max {
                let top_pos = if u >= j { ways[j][u - j] } else { 0.0 };
                let top_neg = if j > 0 { next[j - 1][u] } else { 0.0 };
                next[j][u] = top_pos + top_neg;
            }
        }
        ways = next;
    }
    let all = &ways[n_neg];
    let total: f64 = all.iter().sum();
    all[u_obs..].iter().sum::<f64>() / total
}

/// The two-sided p-value of a directed AUC (`max(AUC, 1 − AUC)`, the direction read from
/// the same data): chance gives one at least this far from ½ either way twice as often.
pub fn directed_auc_p_value(directed_auc: f64, n_pos: usize, n_neg: usize) -> f64 {
    (2.0 * auc_p_value(directed_auc, n_pos, n_neg)).min(1.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn auc_p_values_by_hand() {
        // One of each: the positive is above half the time.
        assert_eq!(auc_p_value(1.0, 1, 1), 0.5);
        assert_eq!(auc_p_value(0.0, 1, 1), 1.0);
        // Two of each: the 6 orders give U = 0, 1, 2, 2, 3, 4.
        assert_eq!(auc_p_value(1.0, 2, 2), 1.0 / 6.0);
        assert_eq!(auc_p_value(0.75, 2, 2), 2.0 / 6.0);
        assert_eq!(auc_p_value(0.5, 2, 2), 4.0 / 6.0);
        // A tie (U = 2.5 of 4 would be AUC 0.625) counts as U = 2.
        assert_eq!(auc_p_value(0.625, 2, 2), 4.0 / 6.0);
        // Two positives, one negative: U = 0, 1, 2 once each.
        assert!((auc_p_value(0.5, 2, 1) - 2.0 / 3.0).abs() < 1e-15);
        // Ten of each, perfect separation: 1 order of C(20, 10) = 184756.
        assert!((auc_p_value(1.0, 10, 10) - 1.0 / 184_756.0).abs() < 1e-18);
        // A directed AUC of ½ is no evidence at all; a perfect one, either way, twice 1/C.
        assert_eq!(directed_auc_p_value(0.5, 10, 10), 1.0);
        assert!((directed_auc_p_value(1.0, 10, 10) - 2.0 / 184_756.0).abs() < 1e-18);
        assert!(auc_p_value(f64::NAN, 2, 2).is_nan() && auc_p_value(1.0, 0, 2).is_nan());
    }

    #[test]
    fn auc_by_hand() {
        // Every positive above every negative, and the reverse.
        assert_eq!(roc_auc(&[3.0, 4.0], &[1.0, 2.0]), 1.0);
        assert_eq!(roc_auc(&[1.0, 2.0], &[3.0, 4.0]), 0.0);
        // Pairs (pos, neg): (2,1) win, (2,3) loss, (4,1) win, (4,3) win → 3/4.
        assert_eq!(roc_auc(&[2.0, 4.0], &[1.0, 3.0]), 0.75);
        // Ties count half: (1,1) ½, (1,0) 1, (2,1) 1, (2,0) 1 → 3.5/4.
        assert_eq!(roc_auc(&[1.0, 2.0], &[1.0, 0.0]), 0.875);
        // All tied: ½.
        assert_eq!(roc_auc(&[5.0, 5.0, 5.0], &[5.0]), 0.5);
        // Three positives, two negatives: (0.9: 2 wins) (0.5: beats 0.1, ties 0.5 → 1.5)
        // (0.2: beats 0.1 → 1) = 4.5/6.
        assert_eq!(roc_auc(&[0.9, 0.5, 0.2], &[0.5, 0.1]), 0.75);
        assert!(roc_auc(&[], &[1.0]).is_nan());
    }

    fn toy() -> (Vec<String>, Vec<Vec<f64>>, Vec<bool>) {
        // Feature "a" separates the classes (stego above 1.0); "b" is noise; "c" is
        // constant and must be dropped; "d" is missing in some rows.
        let names: Vec<String> = ["a", "b", "c", "d"].iter().map(|s| s.to_string()).collect();
        let mut rows = Vec::new();
        let mut labels = Vec::new();
        for i in 0..10 {
            let stego = i % 2 == 1;
            let a = if stego {
                1.5 + 0.1 * i as f64
            } else {
                0.2 + 0.05 * i as f64
            };
            let b = ((i * 7) % 5) as f64;
            let d = if i % 3 == 0 { f64::NAN } else { i as f64 };
            rows.push(vec![a, b, 3.0, d]);
            labels.push(stego);
        }
        (names, rows, labels)
    }

    #[test]
    fn fit_separates_a_separable_set_and_round_trips() {
        let (names, rows, labels) = toy();
        let mut d = Detector::fit(&names, &rows, &labels).unwrap();
        d.fitted_on = "toy".into();
        assert!(
            d.features.iter().all(|f| f.name != "c"),
            "constant feature kept"
        );
        let wa = d.features.iter().find(|f| f.name == "a").unwrap().weight;
        let wb = d.features.iter().find(|f| f.name == "b").unwrap().weight;
        assert!(wa > 1.0 && wa > 2.0 * wb.abs(), "a {wa} b {wb}");
        let scores: Vec<f64> = rows
            .iter()
            .map(|r| {
                d.score(
                    &names
                        .iter()
                        .cloned()
                        .zip(r.iter().copied())
                        .collect::<Vec<_>>(),
                )
            })
            .collect();
        for (s, &y) in scores.iter().zip(&labels) {
            assert!(
                if y { *s > 0.5 } else { *s < 0.5 },
                "score {s} for stego={y}"
            );
        }
        let pos: Vec<f64> = scores
            .iter()
            .zip(&labels)
            .filter(|(_, y)| **y)
            .map(|(s, _)| *s)
            .collect();
        let neg: Vec<f64> = scores
            .iter()
            .zip(&labels)
            .filter(|(_, y)| !**y)
            .map(|(s, _)| *s)
            .collect();
        assert_eq!(roc_auc(&pos, &neg), 1.0);
        // A model missing every feature scores the intercept alone.
        assert_eq!(d.score(&[]), sigmoid(d.bias));
        // Deterministic, and the same through JSON.
        assert_eq!(
            Detector::fit(&names, &rows, &labels).unwrap().features,
            d.features
        );
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("d.json");
        d.save(&p).unwrap();
        // serde_json parses floats to within an ulp, not always exactly.
        let back = Detector::load(&p).unwrap();
        assert_eq!(back.fitted_on, "toy");
        assert_eq!(back.features.len(), d.features.len());
        let close = |a: f64, b: f64| (a - b).abs() <= 1e-14 * a.abs().max(1.0);
        for (f, g) in back.features.iter().zip(&d.features) {
            assert_eq!(f.name, g.name);
            assert!(close(f.mean, g.mean) && close(f.std, g.std) && close(f.weight, g.weight));
        }
        let x = vec![("a".to_string(), 1.9), ("b".to_string(), 2.0)];
        assert!(close(back.score(&x), d.score(&x)));
    }

    #[test]
    fn fit_refuses_one_class_and_ragged_rows() {
        let (names, rows, _) = toy();
        assert!(Detector::fit(&names, &rows, &[true; 10]).is_err());
        assert!(Detector::fit(&names, &rows[..3], &[true, false]).is_err());
        let mut ragged = rows.clone();
        ragged[2].pop();
        assert!(Detector::fit(&names, &ragged, &[true, false].repeat(5)).is_err());
    }

    #[test]
    fn bad_detector_files_are_refused_by_name() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("det.json");
        std::fs::write(&p, "{\"bias\": 1}").unwrap();
        let e = Detector::load(&p).unwrap_err().to_string();
        assert!(e.contains("det.json"), "{e}");
        let e = Detector::load(&dir.path().join("none.json"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("none.json"), "{e}");
    }

    #[test]
    fn feature_matrix_aligns_by_name() {
        let s = vec![
            vec![("x".to_string(), 1.0), ("y".to_string(), 2.0)],
            vec![("y".to_string(), 3.0), ("z".to_string(), 4.0)],
        ];
        let (names, rows) = feature_matrix(&s);
        assert_eq!(names, ["x", "y", "z"]);
        assert_eq!(rows[0][..2], [1.0, 2.0]);
        assert!(rows[0][2].is_nan() && rows[1][0].is_nan());
        assert_eq!(rows[1][1..], [3.0, 4.0]);
    }

    #[test]
    fn the_embedded_detector_loads() {
        let d = Detector::embedded().unwrap();
        assert!(!d.fitted_on.is_empty());
        assert!(!d.features.is_empty());
        let s = d.score(&[]);
        assert!((0.0..=1.0).contains(&s));
    }
}
