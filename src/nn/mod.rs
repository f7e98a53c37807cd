//! f32 multilayer perceptrons on nalgebra: a single-state forward into caller-owned scratch (no
//! allocation after the scratch is made) and a batched forward (matrix-matrix products) over many
//! states.

use nalgebra::{DMatrix, DVector, DVectorView};
use serde::{Deserialize, Serialize};

/// Activation applied after hidden layers.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Activation {
    Relu,
    Tanh,
}

impl Activation {
    #[inline]
    fn apply(self, values: &mut [f32]) {
        match self {
            Activation::Relu => values.iter_mut().for_each(|v| *v = v.max(0.0)),
            Activation::Tanh => values.iter_mut().for_each(|v| *v = v.tanh()),
        }
    }
}

/// One affine layer, PyTorch layout: `weight` is [out, in].
#[derive(Clone, Debug)]
pub struct Dense {
    pub weight: DMatrix<f32>,
    pub bias: DVector<f32>,
}

impl Dense {
    pub fn input_dim(&self) -> usize {
        self.weight.ncols()
    }
    pub fn output_dim(&self) -> usize {
        self.weight.nrows()
    }
    /// Builds a layer from row-major [out, in] weights, as stored in safetensors.
    pub fn from_row_major(out: usize, inp: usize, weight: &[f32], bias: &[f32]) -> Dense {
        Dense {
            weight: DMatrix::from_row_slice(out, inp, weight),
            bias: DVector::from_column_slice(bias),
        }
    }
    /// Row-major [out, in] weights, as stored in safetensors.
    pub fn weight_row_major(&self) -> Vec<f32> {
        self.weight.transpose().as_slice().to_vec()
    }
    /// Stacks layers with the same input into one (e.g. the actor's mu and log_std heads).
    pub fn stack(parts: &[&Dense]) -> Dense {
        let inp = parts[0].input_dim();
        let out: usize = parts.iter().map(|d| d.output_dim()).sum();
        let mut weight = DMatrix::zeros(out, inp);
        let mut bias = DVector::zeros(out);
        let mut row = 0;
        for part in parts {
            let n = part.output_dim();
            weight.rows_mut(row, n).copy_from(&part.weight);
            bias.rows_mut(row, n).copy_from(&part.bias);
            row += n;
        }
        Dense { weight, bias }
    }
    fn flops(&self) -> u64 {
        2 * (self.weight.nrows() * self.weight.ncols()) as u64
    }
}

/// A chain of dense layers. The activation follows every hidden layer, and the last layer too when
/// `activate_output` is set (SB3's `latent_pi` ends in an activation, critics do not).
#[derive(Clone, Debug)]
pub struct Mlp {
    input_dim: usize,
    layers: Vec<Dense>,
    activation: Activation,
    activate_output: bool,
}

/// Per-layer outputs of a single-state forward.
#[derive(Clone, Debug)]
pub struct MlpScratch {
    outputs: Vec<DVector<f32>>,
    input: DVector<f32>,
}

/// Per-layer outputs of a batched forward, [dim, batch] column-major (one column per state).
#[derive(Clone, Debug, Default)]
pub struct BatchScratch {
    outputs: Vec<DMatrix<f32>>,
}

/// A chain whose layer dimensions do not connect.
#[derive(Debug, thiserror::Error)]
#[error("layer {layer} takes {got} inputs but the previous layer gives {expected}")]
pub struct ShapeError {
    pub layer: usize,
    pub expected: usize,
    pub got: usize,
}

impl MlpScratch {
    /// The output of the last forward into this scratch.
    pub fn output(&self) -> &[f32] {
        match self.outputs.last() {
            Some(out) => out.as_slice(),
            None => self.input.as_slice(),
        }
    }
}

impl Mlp {
    pub fn new(
        input_dim: usize,
        layers: Vec<Dense>,
        activation: Activation,
        activate_output: bool,
    ) -> Result<Mlp, ShapeError> {
        let mut width = input_dim;
        for (layer, dense) in layers.iter().enumerate() {
            if dense.input_dim() != width || dense.bias.len() != dense.output_dim() {
                return Err(ShapeError {
                    layer,
                    expected: width,
                    got: dense.input_dim(),
                });
            }
            width = dense.output_dim();
        }
        Ok(Mlp {
            input_dim,
            layers,
            activation,
            activate_output,
        })
    }

    pub fn input_dim(&self) -> usize {
        self.input_dim
    }
    pub fn output_dim(&self) -> usize {
        self.layers.last().map_or(self.input_dim, Dense::output_dim)
    }
    pub fn layers(&self) -> &[Dense] {
        &self.layers
    }
    pub fn activation(&self) -> Activation {
        self.activation
    }
    /// Floating-point operations of one single-state forward (multiply-adds count as two).
    pub fn flops(&self) -> u64 {
        self.layers.iter().map(Dense::flops).sum()
    }

    pub fn scratch(&self) -> MlpScratch {
        MlpScratch {
            outputs: self
                .layers
                .iter()
                .map(|d| DVector::zeros(d.output_dim()))
                .collect(),
            input: DVector::zeros(self.input_dim),
        }
    }

    /// The input buffer of `scratch`, to fill before [`Mlp::forward_scratch_input`] (saves a copy
    /// when the input is assembled from parts).
    pub fn input_buffer<'s>(&self, scratch: &'s mut MlpScratch) -> &'s mut [f32] {
        scratch.input.as_mut_slice()
    }

    /// Forward of one state; the result lives in `scratch`. Does not allocate.
    pub fn forward<'s>(&self, input: &[f32], scratch: &'s mut MlpScratch) -> &'s [f32] {
        assert_eq!(input.len(), self.input_dim, "Mlp::forward input length");
        scratch.input.as_mut_slice().copy_from_slice(input);
        self.forward_scratch_input(scratch)
    }

    /// Forward of the state already written into [`Mlp::input_buffer`].
    pub fn forward_scratch_input<'s>(&self, scratch: &'s mut MlpScratch) -> &'s [f32] {
        let last = self.layers.len();
        for (i, dense) in self.layers.iter().enumerate() {
            let (before, rest) = scratch.outputs.split_at_mut(i);
            let out = &mut rest[0];
            let x = if i == 0 {
                DVectorView::from_slice(scratch.input.as_slice(), self.input_dim)
            } else {
                let prev = &before[i - 1];
                DVectorView::from_slice(prev.as_slice(), prev.len())
            };
            out.copy_from(&dense.bias);
            out.gemv(1.0, &dense.weight, &x, 1.0);
            if i + 1 < last || self.activate_output {
                self.activation.apply(out.as_mut_slice());
            }
        }
        scratch.output()
    }

    /// Forward of two states at once (e.g. Q(s, a) and Q(s, pi(s))), each written into the input
    /// buffer of its scratch: every weight is read once for both, which roughly halves the memory
    /// traffic of two single forwards. Results: [`MlpScratch::output`]. Does not allocate.
    pub fn forward_pair_scratch_inputs(&self, a: &mut MlpScratch, b: &mut MlpScratch) {
        let last = self.layers.len();
        for (i, dense) in self.layers.iter().enumerate() {
            let (a_before, a_rest) = a.outputs.split_at_mut(i);
            let (b_before, b_rest) = b.outputs.split_at_mut(i);
            let (ya, yb) = (&mut a_rest[0], &mut b_rest[0]);
            let (xa, xb) = if i == 0 {
                (a.input.as_slice(), b.input.as_slice())
            } else {
                (a_before[i - 1].as_slice(), b_before[i - 1].as_slice())
            };
            ya.copy_from(&dense.bias);
            yb.copy_from(&dense.bias);
            let (ya, yb) = (ya.as_mut_slice(), yb.as_mut_slice());
            let rows = dense.output_dim();
            // Column-major weights: add column j times x[j], both states per load of the column.
            for (j, column) in dense.weight.as_slice().chunks_exact(rows).enumerate() {
                let (sa, sb) = (xa[j], xb[j]);
                for ((ya, yb), w) in ya.iter_mut().zip(yb.iter_mut()).zip(column) {
                    *ya += w * sa;
                    *yb += w * sb;
                }
            }
            if i + 1 < last || self.activate_output {
                self.activation.apply(ya);
                self.activation.apply(yb);
            }
        }
    }

    /// Forward of many states at once: `inputs` is [input_dim, batch], one column per state. The
    /// result ([output_dim, batch]) lives in `scratch`, whose buffers are reused while the batch
    /// size stays the same.
    pub fn forward_batch<'s>(
        &self,
        inputs: &DMatrix<f32>,
        scratch: &'s mut BatchScratch,
    ) -> &'s DMatrix<f32> {
        assert_eq!(inputs.nrows(), self.input_dim, "Mlp::forward_batch rows");
        let batch = inputs.ncols();
        scratch
            .outputs
            .resize_with(self.layers.len().max(1), || DMatrix::zeros(0, 0));
        if self.layers.is_empty() {
            scratch.outputs[0] = inputs.clone();
            return &scratch.outputs[0];
        }
        let last = self.layers.len();
        for (i, dense) in self.layers.iter().enumerate() {
            let (before, rest) = scratch.outputs.split_at_mut(i);
            let out = &mut rest[0];
            if out.shape() != (dense.output_dim(), batch) {
                *out = DMatrix::zeros(dense.output_dim(), batch);
            }
            for mut column in out.column_iter_mut() {
                column.copy_from(&dense.bias);
            }
            let x = if i == 0 { inputs } else { &before[i - 1] };
            out.gemm(1.0, &dense.weight, x, 1.0);
            if i + 1 < last || self.activate_output {
                self.activation.apply(out.as_mut_slice());
            }
        }
        &scratch.outputs[last - 1]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn layer(out: usize, inp: usize, seed: f32) -> Dense {
        let w: Vec<f32> = (0..out * inp)
            .map(|i| ((i as f32 + seed) * 0.37).sin())
            .collect();
        let b: Vec<f32> = (0..out).map(|i| ((i as f32 - seed) * 0.11).cos()).collect();
        Dense::from_row_major(out, inp, &w, &b)
    }

    fn reference_forward(mlp: &Mlp, x: &[f32]) -> Vec<f32> {
        let mut v = x.to_vec();
        for (i, d) in mlp.layers().iter().enumerate() {
            let mut out = vec![0.0f32; d.output_dim()];
            for (r, o) in out.iter_mut().enumerate() {
                *o = d.bias[r]
                    + (0..d.input_dim())
                        .map(|c| d.weight[(r, c)] * v[c])
                        .sum::<f32>();
            }
            if i + 1 < mlp.layers().len() || mlp.activate_output {
                out.iter_mut().for_each(|o| *o = o.max(0.0));
            }
            v = out;
        }
        v
    }

    #[test]
    fn row_major_layout_matches_pytorch() {
        // weight[out=2, in=3] row-major: row r holds the weights of output r.
        let d = Dense::from_row_major(2, 3, &[1., 2., 3., 4., 5., 6.], &[0.5, -0.5]);
        let mlp = Mlp::new(3, vec![d.clone()], Activation::Relu, false).unwrap();
        let mut s = mlp.scratch();
        assert_eq!(mlp.forward(&[1., 0., -1.], &mut s), &[-1.5, -2.5]);
        assert_eq!(d.weight_row_major(), vec![1., 2., 3., 4., 5., 6.]);
    }

    #[test]
    fn single_and_batched_forward_agree_with_reference() {
        let mlp = Mlp::new(
            5,
            vec![layer(7, 5, 1.0), layer(6, 7, 2.0), layer(2, 6, 3.0)],
            Activation::Relu,
            false,
        )
        .unwrap();
        let states: Vec<Vec<f32>> = (0..4)
            .map(|k| (0..5).map(|i| ((k * 5 + i) as f32 * 0.3).cos()).collect())
            .collect();
        let mut scratch = mlp.scratch();
        let mut batch = DMatrix::zeros(5, states.len());
        for (k, s) in states.iter().enumerate() {
            batch.column_mut(k).copy_from_slice(s);
        }
        let mut bs = BatchScratch::default();
        let out = mlp.forward_batch(&batch, &mut bs).clone();
        for (k, s) in states.iter().enumerate() {
            let expected = reference_forward(&mlp, s);
            let single = mlp.forward(s, &mut scratch);
            for j in 0..2 {
                assert!((single[j] - expected[j]).abs() < 1e-4);
                assert!((out[(j, k)] - expected[j]).abs() < 1e-4);
            }
        }
    }

    #[test]
    fn pair_forward_matches_two_single_forwards() {
        let mlp = Mlp::new(
            5,
            vec![layer(9, 5, 1.0), layer(7, 9, 2.0), layer(1, 7, 3.0)],
            Activation::Relu,
            false,
        )
        .unwrap();
        let (xa, xb) = ([0.3, -0.2, 0.9, 0.1, -0.5], [-0.7, 0.4, 0.2, 0.6, 0.05]);
        let (mut sa, mut sb, mut single) = (mlp.scratch(), mlp.scratch(), mlp.scratch());
        mlp.input_buffer(&mut sa).copy_from_slice(&xa);
        mlp.input_buffer(&mut sb).copy_from_slice(&xb);
        mlp.forward_pair_scratch_inputs(&mut sa, &mut sb);
        let ya = mlp.forward(&xa, &mut single)[0];
        assert!((sa.output()[0] - ya).abs() < 1e-5);
        let yb = mlp.forward(&xb, &mut single)[0];
        assert!((sb.output()[0] - yb).abs() < 1e-5);
        // Identical inputs give bitwise identical outputs (Replan's eps = 0 test relies on it).
        mlp.input_buffer(&mut sb).copy_from_slice(&xa);
        mlp.forward_pair_scratch_inputs(&mut sa, &mut sb);
        assert_eq!(sa.output(), sb.output());
    }

    #[test]
    fn mismatched_chain_is_rejected() {
        let err = Mlp::new(
            5,
            vec![layer(7, 5, 1.0), layer(2, 6, 2.0)],
            Activation::Relu,
            false,
        )
        .unwrap_err();
        assert_eq!((err.layer, err.expected, err.got), (1, 7, 6));
    }
}
