//! The closed-form connection graph of a linear system (docs/method.md §4,
//! Lemma 1): the ground truth CS3 is tested against.

use nalgebra::DMatrix;

/// H = Σ_{t=0}^{m−1} C_t with C_t = |(E^t + E^{t−1} + … + I) F| (element-wise
/// absolute value); m × n, state × action.
pub fn lemma1_h(e: &DMatrix<f64>, f: &DMatrix<f64>) -> DMatrix<f64> {
    let m = e.nrows();
    let mut power = DMatrix::identity(m, m); // E^t
    let mut partial = DMatrix::zeros(m, m); // E^t + … + I
    let mut h = DMatrix::zeros(m, f.ncols());
    for _t in 0..m {
        partial += &power;
        h += (&partial * f).abs();
        power = e * power;
    }
    h
}

/// G (n × m, action × state): G_ij = 1 iff H_ji > 0. This is the pattern of H
/// transposed (the docs/method.md §4 decision on the publication's eq. 10 slip).
pub fn lemma1_graph(e: &DMatrix<f64>, f: &DMatrix<f64>) -> Vec<Vec<u8>> {
    let h = lemma1_h(e, f);
    (0..h.ncols()).map(|i| (0..h.nrows()).map(|j| u8::from(h[(j, i)] > 0.0)).collect()).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paper_example_eq_10() {
        let e = DMatrix::from_row_slice(3, 3, &[-1.0, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]);
        let f = DMatrix::identity(3, 3);
        let h = lemma1_h(&e, &f);
        assert_eq!(h, DMatrix::from_row_slice(3, 3, &[2.0, 2.0, 0.0, 0.0, 6.0, 0.0, 0.0, 0.0, 6.0]));
        assert_eq!(lemma1_graph(&e, &f), vec![vec![1, 0, 0], vec![1, 1, 0], vec![0, 0, 1]]);
    }
}
