//! f32 multilayer perceptrons on nalgebra matrices, evaluated over a batch of states stored as rows
//! (one state per row). One kernel serves a single state (a batch of one) and cross-session
//! batches: each weight column is loaded once per block of states. Buffers live in caller-owned
//! scratch and only grow, so a forward allocates nothing once a batch size has been seen.

use nalgebra::{DMatrix, DVector};
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

/// One affine layer, PyTorch layout: `weight` is [out, in] (stored column-major, so a column is
/// the weights of one input).
#[derive(Clone, Debug)]
pub struct Dense {
    pub weight: DMatrix<f32>,
    pub bias: DVector<f32>,
}

/// States per block of the kernel: the block's outputs stay in L1 while a weight column is reused.
const BLOCK_ROWS: usize = 8;

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
    fn flops(&self) -> u64 {
        2 * (self.weight.nrows() * self.weight.ncols()) as u64
    }

    /// `outputs[k] = W inputs[k] + b` for every row k: `inputs` is [n, in], `outputs` [n, out].
    /// A row's result does not depend on the other rows. Uses AVX-512 or AVX2 + FMA register
    /// tiles when the CPU has them (chosen at run time, so one build serves every x86-64); every
    /// SIMD path computes each output as the same chain of fused multiply-adds, so they agree
    /// bit for bit.
    pub fn forward_rows(&self, inputs: &[f32], outputs: &mut [f32]) {
        let (out, inp) = (self.output_dim(), self.input_dim());
        debug_assert_eq!(inputs.len() % inp, 0);
        debug_assert_eq!(outputs.len(), inputs.len() / inp * out);
        for row in outputs.chunks_exact_mut(out) {
            row.copy_from_slice(self.bias.as_slice());
        }
        let weights = self.weight.as_slice();
        #[cfg(target_arch = "x86_64")]
        if std::is_x86_feature_detected!("avx512f") {
            // SAFETY: the CPU has the features the function is compiled for.
            unsafe { accumulate_avx512(weights, out, inp, inputs, outputs) };
            return;
        }
        #[cfg(target_arch = "x86_64")]
        if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
            // SAFETY: the CPU has the features the function is compiled for.
            unsafe { accumulate_avx2_fma(weights, out, inp, inputs, outputs) };
            return;
        }
        accumulate(weights, out, inp, inputs, outputs);
    }
}

/// `outputs[k] += W inputs[k]`, W column-major [out, inp], for CPUs without AVX2: each weight
/// column is loaded once per block of rows and added into the block's outputs, which stay in L1.
/// The same fused multiply-add chain as the SIMD kernels, so every machine gives the same bits.
fn accumulate(weights: &[f32], out: usize, inp: usize, inputs: &[f32], outputs: &mut [f32]) {
    let n = inputs.len() / inp;
    for block in (0..n).step_by(BLOCK_ROWS) {
        let rows = block..(block + BLOCK_ROWS).min(n);
        for (j, column) in weights.chunks_exact(out).enumerate() {
            for k in rows.clone() {
                let x = inputs[k * inp + j];
                let y = &mut outputs[k * out..(k + 1) * out];
                for (y, &w) in y.iter_mut().zip(column) {
                    *y = w.mul_add(x, *y);
                }
            }
        }
    }
}

/// The AVX2 + FMA kernel: register tiles of 16 outputs x R rows accumulate over the inputs in
/// order (the same order as the scalar remainder), so every output is the same whatever the
/// batch size or the tile it falls in.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn accumulate_avx2_fma(
    weights: &[f32],
    out: usize,
    inp: usize,
    inputs: &[f32],
    outputs: &mut [f32],
) {
    let n = inputs.len() / inp;
    let mut row = 0;
    while row < n {
        let rows = (n - row).min(4);
        // SAFETY: the tiles index within weights [inp * out], inputs [n * inp], outputs [n * out].
        unsafe {
            match rows {
                4 => tile_rows::<4>(
                    weights,
                    out,
                    inp,
                    &inputs[row * inp..],
                    &mut outputs[row * out..],
                ),
                3 => tile_rows::<3>(
                    weights,
                    out,
                    inp,
                    &inputs[row * inp..],
                    &mut outputs[row * out..],
                ),
                2 => tile_rows::<2>(
                    weights,
                    out,
                    inp,
                    &inputs[row * inp..],
                    &mut outputs[row * out..],
                ),
                _ => tile_rows::<1>(
                    weights,
                    out,
                    inp,
                    &inputs[row * inp..],
                    &mut outputs[row * out..],
                ),
            }
        }
        row += rows;
    }
}

/// The AVX-512 kernel: register tiles of 32 outputs x up to 6 rows, otherwise as the AVX2 one.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn accumulate_avx512(
    weights: &[f32],
    out: usize,
    inp: usize,
    inputs: &[f32],
    outputs: &mut [f32],
) {
    let n = inputs.len() / inp;
    let mut row = 0;
    while row < n {
        let rows = (n - row).min(6);
        let (x, y) = (&inputs[row * inp..], &mut outputs[row * out..]);
        // SAFETY: the tiles index within weights [inp * out], inputs [n * inp], outputs [n * out].
        unsafe {
            match rows {
                6 => tile_rows_512::<6>(weights, out, inp, x, y),
                5 => tile_rows_512::<5>(weights, out, inp, x, y),
                4 => tile_rows_512::<4>(weights, out, inp, x, y),
                3 => tile_rows_512::<3>(weights, out, inp, x, y),
                2 => tile_rows_512::<2>(weights, out, inp, x, y),
                _ => tile_rows_512::<1>(weights, out, inp, x, y),
            }
        }
        row += rows;
    }
}

/// R rows of the AVX-512 kernel: `inputs` and `outputs` start at the first of them.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn tile_rows_512<const R: usize>(
    weights: &[f32],
    out: usize,
    inp: usize,
    inputs: &[f32],
    outputs: &mut [f32],
) {
    use std::arch::x86_64::*;
    assert!(weights.len() >= inp * out && inputs.len() >= R * inp && outputs.len() >= R * out);
    let (w, x, y) = (weights.as_ptr(), inputs.as_ptr(), outputs.as_mut_ptr());
    let mut o = 0;
    // SAFETY: o + 32 <= out, r < R and j < inp keep every pointer inside the checked lengths.
    unsafe {
        while o + 32 <= out {
            let mut lo = [_mm512_setzero_ps(); R];
            let mut hi = [_mm512_setzero_ps(); R];
            for r in 0..R {
                lo[r] = _mm512_loadu_ps(y.add(r * out + o));
                hi[r] = _mm512_loadu_ps(y.add(r * out + o + 16));
            }
            for j in 0..inp {
                let w_lo = _mm512_loadu_ps(w.add(j * out + o));
                let w_hi = _mm512_loadu_ps(w.add(j * out + o + 16));
                for r in 0..R {
                    let xv = _mm512_set1_ps(*x.add(r * inp + j));
                    lo[r] = _mm512_fmadd_ps(w_lo, xv, lo[r]);
                    hi[r] = _mm512_fmadd_ps(w_hi, xv, hi[r]);
                }
            }
            for r in 0..R {
                _mm512_storeu_ps(y.add(r * out + o), lo[r]);
                _mm512_storeu_ps(y.add(r * out + o + 16), hi[r]);
            }
            o += 32;
        }
    }
    scalar_remainder::<R>(weights, out, inp, inputs, outputs, o);
}

/// Outputs from `from` on, one fused multiply-add at a time in the kernels' order.
#[inline(always)]
fn scalar_remainder<const R: usize>(
    weights: &[f32],
    out: usize,
    inp: usize,
    inputs: &[f32],
    outputs: &mut [f32],
    from: usize,
) {
    for o in from..out {
        for r in 0..R {
            let mut acc = outputs[r * out + o];
            for j in 0..inp {
                acc = weights[j * out + o].mul_add(inputs[r * inp + j], acc);
            }
            outputs[r * out + o] = acc;
        }
    }
}

/// R rows of the AVX2 kernel: `inputs` and `outputs` start at the first of them.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn tile_rows<const R: usize>(
    weights: &[f32],
    out: usize,
    inp: usize,
    inputs: &[f32],
    outputs: &mut [f32],
) {
    use std::arch::x86_64::*;
    assert!(weights.len() >= inp * out && inputs.len() >= R * inp && outputs.len() >= R * out);
    let (w, x, y) = (weights.as_ptr(), inputs.as_ptr(), outputs.as_mut_ptr());
    let mut o = 0;
    // SAFETY: o + 16 <= out, r < R and j < inp keep every pointer inside the checked lengths.
    unsafe {
        while o + 16 <= out {
            let mut lo = [_mm256_setzero_ps(); R];
            let mut hi = [_mm256_setzero_ps(); R];
            for r in 0..R {
                lo[r] = _mm256_loadu_ps(y.add(r * out + o));
                hi[r] = _mm256_loadu_ps(y.add(r * out + o + 8));
            }
            for j in 0..inp {
                let w_lo = _mm256_loadu_ps(w.add(j * out + o));
                let w_hi = _mm256_loadu_ps(w.add(j * out + o + 8));
                for r in 0..R {
                    let xv = _mm256_set1_ps(*x.add(r * inp + j));
                    lo[r] = _mm256_fmadd_ps(w_lo, xv, lo[r]);
                    hi[r] = _mm256_fmadd_ps(w_hi, xv, hi[r]);
                }
            }
            for r in 0..R {
                _mm256_storeu_ps(y.add(r * out + o), lo[r]);
                _mm256_storeu_ps(y.add(r * out + o + 8), hi[r]);
            }
            o += 16;
        }
    }
    scalar_remainder::<R>(weights, out, inp, inputs, outputs, o);
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

/// Per-layer outputs of a forward; they grow to the largest batch seen and are reused.
#[derive(Clone, Debug, Default)]
pub struct MlpScratch {
    outputs: Vec<Vec<f32>>,
}

/// A chain whose layer dimensions do not connect.
#[derive(Debug, thiserror::Error)]
#[error("layer {layer} takes {got} inputs but the previous layer gives {expected}")]
pub struct ShapeError {
    pub layer: usize,
    pub expected: usize,
    pub got: usize,
}

/// Sets `buffer` to `len` values, allocating only when it has never been that long.
pub fn resize(buffer: &mut Vec<f32>, len: usize) {
    buffer.resize(len, 0.0);
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
    /// Floating-point operations of one state's forward (multiply-adds count as two).
    pub fn flops(&self) -> u64 {
        self.layers.iter().map(Dense::flops).sum()
    }

    pub fn scratch(&self) -> MlpScratch {
        self.scratch_for(1)
    }

    /// Scratch with room for batches of up to `rows` states.
    pub fn scratch_for(&self, rows: usize) -> MlpScratch {
        MlpScratch {
            outputs: self
                .layers
                .iter()
                .map(|d| Vec::with_capacity(rows * d.output_dim()))
                .collect(),
        }
    }

    /// Forward of n states: `inputs` is [n, input_dim] row-major; the result ([n, output_dim])
    /// lives in `scratch`. Allocates only when n exceeds every earlier batch.
    pub fn forward_rows<'s>(&self, inputs: &'s [f32], scratch: &'s mut MlpScratch) -> &'s [f32] {
        assert_eq!(
            inputs.len() % self.input_dim,
            0,
            "Mlp::forward_rows input length"
        );
        let n = inputs.len() / self.input_dim;
        scratch.outputs.resize_with(self.layers.len(), Vec::new);
        let last = self.layers.len();
        for (i, dense) in self.layers.iter().enumerate() {
            let (before, rest) = scratch.outputs.split_at_mut(i);
            let out = &mut rest[0];
            resize(out, n * dense.output_dim());
            let x = if i == 0 { inputs } else { &before[i - 1][..] };
            dense.forward_rows(x, out);
            if i + 1 < last || self.activate_output {
                self.activation.apply(out);
            }
        }
        match scratch.outputs.last() {
            Some(out) => out,
            None => inputs,
        }
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

    fn chain() -> Mlp {
        Mlp::new(
            5,
            vec![layer(7, 5, 1.0), layer(6, 7, 2.0), layer(2, 6, 3.0)],
            Activation::Relu,
            false,
        )
        .unwrap()
    }

    #[test]
    fn row_major_layout_matches_pytorch() {
        // weight[out=2, in=3] row-major: row r holds the weights of output r.
        let d = Dense::from_row_major(2, 3, &[1., 2., 3., 4., 5., 6.], &[0.5, -0.5]);
        let mlp = Mlp::new(3, vec![d.clone()], Activation::Relu, false).unwrap();
        let mut s = mlp.scratch();
        assert_eq!(mlp.forward_rows(&[1., 0., -1.], &mut s), &[-1.5, -2.5]);
        assert_eq!(d.weight_row_major(), vec![1., 2., 3., 4., 5., 6.]);
    }

    #[test]
    fn batches_of_any_size_agree_with_the_reference() {
        let mlp = chain();
        // 19 states: two full blocks of 8 and a partial one; some inputs exactly zero.
        let states: Vec<Vec<f32>> = (0..19)
            .map(|k| {
                (0..5)
                    .map(|i| {
                        if (k + i) % 4 == 0 {
                            0.0
                        } else {
                            ((k * 5 + i) as f32 * 0.3).cos()
                        }
                    })
                    .collect()
            })
            .collect();
        let rows: Vec<f32> = states.concat();
        let mut scratch = mlp.scratch();
        let batched = mlp.forward_rows(&rows, &mut scratch).to_vec();
        let mut single_scratch = mlp.scratch();
        for (k, s) in states.iter().enumerate() {
            let expected = reference_forward(&mlp, s);
            let single = mlp.forward_rows(s, &mut single_scratch);
            for j in 0..2 {
                assert!((single[j] - expected[j]).abs() < 1e-4);
                // A row's result does not depend on its batch.
                assert_eq!(batched[k * 2 + j], single[j]);
            }
        }
    }

    #[test]
    fn wide_layers_use_full_tiles_and_remainders_correctly() {
        // 37 outputs: two 16-wide register tiles and 5 scalar ones; 11 rows: tiles of 4, 4, 3.
        let d = layer(37, 23, 4.0);
        let inputs: Vec<f32> = (0..11 * 23).map(|i| (i as f32 * 0.13).sin()).collect();
        let mut outputs = vec![0.0; 11 * 37];
        d.forward_rows(&inputs, &mut outputs);
        for k in 0..11 {
            for o in 0..37 {
                let expected: f32 = d.bias[o]
                    + (0..23)
                        .map(|j| d.weight[(o, j)] * inputs[k * 23 + j])
                        .sum::<f32>();
                assert!(
                    (outputs[k * 37 + o] - expected).abs() < 1e-4,
                    "row {k} out {o}"
                );
            }
        }
    }

    #[test]
    fn scratch_stops_allocating_once_grown() {
        let mlp = chain();
        let mut scratch = mlp.scratch();
        mlp.forward_rows(&[0.5; 5 * 16], &mut scratch);
        let pointers: Vec<*const f32> = scratch.outputs.iter().map(|o| o.as_ptr()).collect();
        mlp.forward_rows(&[0.5; 5 * 3], &mut scratch);
        mlp.forward_rows(&[0.5; 5 * 16], &mut scratch);
        let after: Vec<*const f32> = scratch.outputs.iter().map(|o| o.as_ptr()).collect();
        assert_eq!(pointers, after);
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
