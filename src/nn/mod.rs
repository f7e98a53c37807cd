//! f32 multilayer perceptrons on nalgebra matrices, evaluated over a batch of states stored as rows
//! (one state per row). One kernel serves a single state (a batch of one) and cross-session
//! batches: weights are packed into panels of 16 outputs, and a register tile (AVX2: 8-output
//! vectors by rows, e.g. one panel by up to 6 states or 12 vectors of one state; AVX-512: two
//! panels by up to 12 states) keeps its accumulators in registers.
//! Buffers live in caller-owned scratch and only grow, so a forward allocates nothing once a batch
//! size has been seen.

use std::sync::atomic::{AtomicU8, Ordering};

use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

/// The dense layers' code path: register tiles for the widest vectors the CPU has, or a named one.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Kernel {
    /// The widest the CPU has: AVX-512, else AVX2 + FMA, else scalar.
    Auto,
    Avx512,
    Avx2,
    Scalar,
}

/// The kernel every dense layer uses ([`use_kernel`]); `Kernel::Auto as u8` until set.
static KERNEL: AtomicU8 = AtomicU8::new(Kernel::Auto as u8);

/// Makes every dense layer of this process use `kernel`, so that a benchmark can compare the
/// paths on one CPU; refused when the CPU lacks its features. Every path gives the same bits.
pub fn use_kernel(kernel: Kernel) -> Result<(), String> {
    #[cfg(target_arch = "x86_64")]
    let supported = match kernel {
        Kernel::Auto | Kernel::Scalar => true,
        Kernel::Avx512 => std::is_x86_feature_detected!("avx512f"),
        Kernel::Avx2 => {
            std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma")
        }
    };
    #[cfg(not(target_arch = "x86_64"))]
    let supported = matches!(kernel, Kernel::Auto | Kernel::Scalar);
    if !supported {
        return Err(format!("this CPU cannot run the {kernel:?} kernel"));
    }
    KERNEL.store(kernel as u8, Ordering::Relaxed);
    Ok(())
}

/// The kernel in use: the one set by [`use_kernel`], else the widest the CPU has.
pub fn kernel() -> Kernel {
    match KERNEL.load(Ordering::Relaxed) {
        k if k == Kernel::Avx512 as u8 => Kernel::Avx512,
        k if k == Kernel::Avx2 as u8 => Kernel::Avx2,
        k if k == Kernel::Scalar as u8 => Kernel::Scalar,
        _ => widest_kernel(),
    }
}

fn widest_kernel() -> Kernel {
    #[cfg(target_arch = "x86_64")]
    {
        if std::is_x86_feature_detected!("avx512f") {
            return Kernel::Avx512;
        }
        if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
            return Kernel::Avx2;
        }
    }
    Kernel::Scalar
}

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
            Activation::Relu => values.iter_mut().for_each(|v| *v = relu(*v)),
            Activation::Tanh => values.iter_mut().for_each(|v| *v = v.tanh()),
        }
    }
}

/// max(v, 0), with 0 for NaN and for -0: the kernels' `max_ps(v, 0)` bit for bit.
#[inline]
fn relu(v: f32) -> f32 {
    if v > 0.0 { v } else { 0.0 }
}

/// One affine layer, PyTorch layout: `weight` is [out, in]. The kernels read a packed copy made
/// once at construction, so the weights are immutable.
#[derive(Clone, Debug)]
pub(crate) struct Dense {
    weight: DMatrix<f32>,
    bias: DVector<f32>,
    /// Panels of [`PANEL`] outputs; within a panel, each input's weights are contiguous
    /// ([panel][input][PANEL]), so a register tile streams one panel from L1. The last panel and
    /// `padded_bias` are padded with zeros.
    packed: Vec<f32>,
    padded_bias: Vec<f32>,
}

/// Outputs per panel of packed weights: two AVX2 registers or one AVX-512 register.
const PANEL: usize = 16;
/// Outputs per AVX2 register: half a panel.
#[cfg(target_arch = "x86_64")]
const LANES: usize = 8;
/// Layers of at most this many outputs (heads) put 8 rows in a vector's lanes, not 8 outputs.
#[cfg(target_arch = "x86_64")]
const ROWS_IN_LANES_OUTPUTS: usize = 4;

impl Dense {
    pub(crate) fn new(weight: DMatrix<f32>, bias: DVector<f32>) -> Dense {
        let (out, inp) = weight.shape();
        let panels = out.div_ceil(PANEL);
        let mut packed = vec![0.0; panels * inp * PANEL];
        for p in 0..panels {
            for j in 0..inp {
                for lane in 0..PANEL.min(out - p * PANEL) {
                    packed[(p * inp + j) * PANEL + lane] = weight[(p * PANEL + lane, j)];
                }
            }
        }
        let mut padded_bias = vec![0.0; panels * PANEL];
        padded_bias[..bias.len()].copy_from_slice(bias.as_slice());
        Dense {
            weight,
            bias,
            packed,
            padded_bias,
        }
    }
    pub(crate) fn input_dim(&self) -> usize {
        self.weight.ncols()
    }
    pub(crate) fn output_dim(&self) -> usize {
        self.weight.nrows()
    }
    /// The [out, in] weights.
    pub(crate) fn weight(&self) -> &DMatrix<f32> {
        &self.weight
    }
    pub(crate) fn bias(&self) -> &DVector<f32> {
        &self.bias
    }
    /// Builds a layer from row-major [out, in] weights, as stored in safetensors.
    pub(crate) fn from_row_major(out: usize, inp: usize, weight: &[f32], bias: &[f32]) -> Dense {
        Dense::new(
            DMatrix::from_row_slice(out, inp, weight),
            DVector::from_column_slice(bias),
        )
    }
    /// Row-major [out, in] weights, as stored in safetensors.
    pub(crate) fn weight_row_major(&self) -> Vec<f32> {
        self.weight.transpose().as_slice().to_vec()
    }
    pub(crate) fn flops(&self) -> u64 {
        2 * (self.weight.nrows() * self.weight.ncols()) as u64
    }

    /// `outputs[k] = W inputs[k] + b` for every row k: `inputs` is [n, in], `outputs` [n, out].
    /// Uses AVX-512 or AVX2 + FMA register tiles when the CPU has them (chosen at run time, so
    /// one build serves every x86-64). Every path computes each output as the same chain of fused
    /// multiply-adds (from the bias, over the inputs in order), so they agree bit for bit and a
    /// row's result does not depend on the other rows.
    pub(crate) fn forward_rows(&self, inputs: &[f32], outputs: &mut [f32]) {
        self.forward(inputs, outputs, false);
    }

    /// `forward_rows` then [`relu`] on every output, applied in registers before the store.
    pub(crate) fn forward_rows_relu(&self, inputs: &[f32], outputs: &mut [f32]) {
        self.forward(inputs, outputs, true);
    }

    fn forward(&self, inputs: &[f32], outputs: &mut [f32], relu: bool) {
        let (out, inp) = (self.output_dim(), self.input_dim());
        assert!(
            inp > 0
                && inputs.len().is_multiple_of(inp)
                && outputs.len() == inputs.len() / inp * out
        );
        match kernel() {
            #[cfg(target_arch = "x86_64")]
            // SAFETY: `kernel` names AVX-512 only where the CPU has it.
            Kernel::Avx512 => unsafe {
                match relu {
                    true => self.forward_avx512::<true>(inputs, outputs),
                    false => self.forward_avx512::<false>(inputs, outputs),
                }
            },
            #[cfg(target_arch = "x86_64")]
            // SAFETY: `kernel` names AVX2 only where the CPU has it and FMA.
            Kernel::Avx2 => unsafe {
                match relu {
                    true => self.forward_avx2::<true>(inputs, outputs),
                    false => self.forward_avx2::<false>(inputs, outputs),
                }
            },
            _ => match relu {
                true => self.forward_scalar::<true>(inputs, outputs),
                false => self.forward_scalar::<false>(inputs, outputs),
            },
        }
    }

    /// The kernels' arithmetic one output at a time, for CPUs without AVX2 (and as the tests'
    /// reference): the same fused multiply-add chain, so every machine gives the same bits.
    fn forward_scalar<const RELU: bool>(&self, inputs: &[f32], outputs: &mut [f32]) {
        let (out, inp) = (self.output_dim(), self.input_dim());
        for (x, y) in inputs.chunks_exact(inp).zip(outputs.chunks_exact_mut(out)) {
            for (o, y) in y.iter_mut().enumerate() {
                let panel = &self.packed[(o / PANEL) * inp * PANEL..];
                let mut acc = self.bias[o];
                for (j, &x) in x.iter().enumerate() {
                    acc = panel[j * PANEL + o % PANEL].mul_add(x, acc);
                }
                *y = if RELU { relu(acc) } else { acc };
            }
        }
    }

    /// The AVX2 + FMA kernel: tiles of consecutive 8-output vectors by rows, about 12
    /// accumulators in registers. Each output's chain of FMAs is serial (the bits depend on its
    /// order), so a tile needs about 8 independent chains to cover the FMA's latency: one row
    /// takes 12 vectors at a time, two rows 4, three 3 (wider tiles of several rows spill
    /// registers); more rows take two vectors (one panel, in L1 while the rows stream) by up to
    /// 6 rows, and a lone vector (a head of at most 8 outputs) up to 12 rows, so a narrow head
    /// computes no padding beyond its 8 lanes. A head of at most 4 outputs puts 8 rows in the
    /// lanes instead, while 8 rows or more are left.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn forward_avx2<const RELU: bool>(&self, inputs: &[f32], outputs: &mut [f32]) {
        let (out, inp) = (self.output_dim(), self.input_dim());
        let n = inputs.len() / inp;
        if n == 0 {
            return;
        }
        let vectors = out.div_ceil(LANES);
        let group = match n {
            1 => 12,
            2 => 4,
            3 => 3,
            _ => 2,
        };
        if out <= ROWS_IN_LANES_OUTPUTS && n >= LANES {
            let lanes = n / LANES * LANES;
            // SAFETY: the CPU has AVX2 and FMA (this function's features).
            unsafe { self.avx2_rows_in_lanes::<RELU>(lanes, inputs, outputs) };
            // SAFETY: as above; the rest is fewer than 8 rows, so this does not come back here.
            unsafe {
                self.forward_avx2::<RELU>(&inputs[lanes * inp..], &mut outputs[lanes * out..])
            };
            return;
        }
        let mut vector = 0;
        while vector < vectors {
            let width = group.min(vectors - vector);
            let most_rows = match (n, width) {
                (1..=3, _) => n,
                (_, 1) => 12,
                _ => 6,
            };
            // Rows split evenly (8 as 4 + 4, not 6 + 2), so no tile is left with few chains.
            let rows = n.div_ceil(n.div_ceil(most_rows));
            let mut row = 0;
            while row < n {
                let r = rows.min(n - row);
                let (x, y) = (&inputs[row * inp..], &mut outputs[row * out..]);
                // SAFETY: the CPU has AVX2 and FMA (this function's features).
                unsafe { self.avx2_tile::<RELU>(r, width, vector, x, y) };
                row += r;
            }
            vector += width;
        }
    }

    /// `rows` rows through `width` vectors from `vector` on, dispatched to a tile whose
    /// accumulators the compiler keeps in registers.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn avx2_tile<const RELU: bool>(
        &self,
        rows: usize,
        width: usize,
        vector: usize,
        x: &[f32],
        y: &mut [f32],
    ) {
        macro_rules! tiles {
            ($(($r:literal, $g:literal)),* $(,)?) => {
                match (rows, width) {
                    // SAFETY: the CPU has AVX2 and FMA (this function's features).
                    $(($r, $g) => unsafe { self.avx2::<$r, $g, RELU>(vector, x, y) },)*
                    _ => unreachable!("{rows} rows by {width} vectors"),
                }
            };
        }
        tiles!(
            (1, 1),
            (1, 2),
            (1, 3),
            (1, 4),
            (1, 5),
            (1, 6),
            (1, 7),
            (1, 8),
            (1, 9),
            (1, 10),
            (1, 11),
            (1, 12),
            (2, 1),
            (2, 2),
            (2, 3),
            (2, 4),
            (3, 1),
            (3, 2),
            (3, 3),
            (4, 1),
            (4, 2),
            (5, 1),
            (5, 2),
            (6, 1),
            (6, 2),
            (7, 1),
            (8, 1),
            (9, 1),
            (10, 1),
            (11, 1),
            (12, 1),
        )
    }

    /// R rows through G consecutive 8-output vectors from `vector` on: `x` and `y` start at the
    /// first of the rows. A vector is one half of a packed panel.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn avx2<const R: usize, const G: usize, const RELU: bool>(
        &self,
        vector: usize,
        x: &[f32],
        y: &mut [f32],
    ) {
        use std::arch::x86_64::*;
        let (out, inp) = (self.output_dim(), self.input_dim());
        assert!(vector + G <= out.div_ceil(LANES));
        assert!(x.len() >= R * inp && y.len() >= R * out);
        // Where each vector's weights for input 0 start: [panel][input][PANEL], the vector's half.
        let start: [usize; G] =
            std::array::from_fn(|g| (vector + g) / 2 * inp * PANEL + (vector + g) % 2 * LANES);
        let (w, xs) = (self.packed.as_ptr(), x.as_ptr());
        // SAFETY: every vector lies inside a panel (asserted above), and j < inp and r < R keep
        // every read inside the lengths checked above; every store writes only outputs that exist.
        unsafe {
            let bias: [__m256; G] = std::array::from_fn(|g| {
                _mm256_loadu_ps(self.padded_bias.as_ptr().add((vector + g) * LANES))
            });
            let mut acc = [bias; R];
            for j in 0..inp {
                let wv: [__m256; G] =
                    std::array::from_fn(|g| _mm256_loadu_ps(w.add(start[g] + j * PANEL)));
                for (r, acc) in acc.iter_mut().enumerate() {
                    let xv = _mm256_broadcast_ss(&*xs.add(r * inp + j));
                    for g in 0..G {
                        acc[g] = _mm256_fmadd_ps(wv[g], xv, acc[g]);
                    }
                }
            }
            let zero = _mm256_setzero_ps();
            let lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
            for (r, acc) in acc.iter().enumerate() {
                for (g, &acc) in acc.iter().enumerate() {
                    // max(acc, 0) gives 0 for NaN and -0, as `relu` does.
                    let acc = if RELU { _mm256_max_ps(acc, zero) } else { acc };
                    let first = (vector + g) * LANES;
                    let row = y.as_mut_ptr().add(r * out + first);
                    let present = LANES.min(out - first);
                    if present == LANES {
                        _mm256_storeu_ps(row, acc);
                    } else {
                        let mask = _mm256_cmpgt_epi32(_mm256_set1_epi32(present as i32), lane);
                        _mm256_maskstore_ps(row, mask, acc);
                    }
                }
            }
        }
    }

    /// A narrow layer (a head) with rows in the lanes: 8 rows per vector, one vector per output,
    /// so no lane computes padding. Each lane runs its row's chain over the inputs in order, the
    /// same bits as the scalar chain. Takes the first `n` rows, a multiple of 8.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn avx2_rows_in_lanes<const RELU: bool>(
        &self,
        n: usize,
        inputs: &[f32],
        outputs: &mut [f32],
    ) {
        macro_rules! widths {
            ($($o:literal),*) => {
                match self.output_dim() {
                    // SAFETY: the CPU has AVX2 and FMA (this function's features).
                    $($o => unsafe { self.avx2_lanes::<$o, RELU>(n, inputs, outputs) },)*
                    out => unreachable!("{out} outputs with rows in lanes"),
                }
            };
        }
        widths!(1, 2, 3, 4)
    }

    /// [`Dense::avx2_rows_in_lanes`] for O outputs. Four inputs of 8 rows at a time are
    /// transposed in registers: row r's inputs j..j+4 and row r+4's load as one vector, and a
    /// 4x4 transpose in each 128-bit half leaves input j of the 8 rows in one vector.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn avx2_lanes<const O: usize, const RELU: bool>(
        &self,
        n: usize,
        inputs: &[f32],
        outputs: &mut [f32],
    ) {
        use std::arch::x86_64::*;
        let inp = self.input_dim();
        assert!(O == self.output_dim() && O <= PANEL && n.is_multiple_of(LANES));
        assert!(inputs.len() >= n * inp && outputs.len() >= n * O);
        // One panel: output o's weight for input j is packed[j * PANEL + o].
        let w = self.packed.as_ptr();
        // SAFETY: rows < n and j < inp keep every read inside the lengths checked above, and
        // o < O <= PANEL inside the one panel; every store is inside `outputs`.
        unsafe {
            for first in (0..n).step_by(LANES) {
                let x = inputs.as_ptr().add(first * inp);
                let mut acc = [_mm256_setzero_ps(); O];
                for (o, acc) in acc.iter_mut().enumerate() {
                    *acc = _mm256_set1_ps(self.bias[o]);
                }
                // Macros, not closures: a closure would not inherit this function's features,
                // and the intrinsics would not be inlined into it.
                macro_rules! fma {
                    ($j:expr, $column:expr) => {{
                        let column = $column;
                        for (o, acc) in acc.iter_mut().enumerate() {
                            let weight = _mm256_broadcast_ss(&*w.add($j * PANEL + o));
                            *acc = _mm256_fmadd_ps(weight, column, *acc);
                        }
                    }};
                }
                let mut j = 0;
                while j + 4 <= inp {
                    let row = x.add(j);
                    macro_rules! pair {
                        ($r:expr) => {
                            _mm256_loadu2_m128(row.add(($r + 4) * inp), row.add($r * inp))
                        };
                    }
                    let (a, b, c, d) = (pair!(0), pair!(1), pair!(2), pair!(3));
                    let (ab_lo, ab_hi) = (_mm256_unpacklo_ps(a, b), _mm256_unpackhi_ps(a, b));
                    let (cd_lo, cd_hi) = (_mm256_unpacklo_ps(c, d), _mm256_unpackhi_ps(c, d));
                    fma!(j, _mm256_shuffle_ps::<0x44>(ab_lo, cd_lo));
                    fma!(j + 1, _mm256_shuffle_ps::<0xEE>(ab_lo, cd_lo));
                    fma!(j + 2, _mm256_shuffle_ps::<0x44>(ab_hi, cd_hi));
                    fma!(j + 3, _mm256_shuffle_ps::<0xEE>(ab_hi, cd_hi));
                    j += 4;
                }
                while j < inp {
                    let row = x.add(j);
                    let at = |r: usize| *row.add(r * inp);
                    fma!(
                        j,
                        _mm256_setr_ps(at(0), at(1), at(2), at(3), at(4), at(5), at(6), at(7))
                    );
                    j += 1;
                }
                let zero = _mm256_setzero_ps();
                for (o, &acc) in acc.iter().enumerate() {
                    // max(acc, 0) gives 0 for NaN and -0, as `relu` does.
                    let acc = if RELU { _mm256_max_ps(acc, zero) } else { acc };
                    let mut rows = [0.0f32; LANES];
                    _mm256_storeu_ps(rows.as_mut_ptr(), acc);
                    for (r, &v) in rows.iter().enumerate() {
                        *outputs.get_unchecked_mut((first + r) * O + o) = v;
                    }
                }
            }
        }
    }

    /// The AVX-512 kernel: tiles of two panels (32 outputs) by up to 12 rows, 24 accumulators in
    /// registers, so each broadcast input feeds two fused multiply-adds and each weight load 12.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f")]
    unsafe fn forward_avx512<const RELU: bool>(&self, inputs: &[f32], outputs: &mut [f32]) {
        let inp = self.input_dim();
        let n = inputs.len() / inp;
        if (1..=3).contains(&n) {
            // Few rows: each output's chain of FMAs is serial (the bits depend on its order),
            // so a tile needs about 8 chains in flight to cover the FMA's latency. One or two
            // rows take 8 panels at a time (8 or 16 accumulators), three rows 4 (12).
            for tile in self.tiles(if n == 3 { 4 } else { 8 }) {
                // SAFETY: the CPU has AVX-512F (this function's feature).
                unsafe { tile.avx512_few_rows::<RELU>(n, inputs, outputs) }
            }
            return;
        }
        for tile in self.tiles(2) {
            // SAFETY: the CPU has AVX-512F (this function's feature).
            unsafe {
                match tile.panels {
                    2 => tile.avx512_rows::<2, RELU>(n, inputs, outputs),
                    _ => tile.avx512_rows::<1, RELU>(n, inputs, outputs),
                }
            }
        }
    }

    /// The packed weights in groups of up to `group` consecutive panels, each with where its
    /// outputs go.
    #[cfg(target_arch = "x86_64")]
    fn tiles(&self, group: usize) -> impl Iterator<Item = Tile<'_>> {
        let (out, inp) = (self.output_dim(), self.input_dim());
        let panels = out.div_ceil(PANEL);
        (0..panels).step_by(group).map(move |p| {
            let end = (p + group).min(panels);
            Tile {
                panel: &self.packed[p * inp * PANEL..end * inp * PANEL],
                bias: &self.padded_bias[p * PANEL..end * PANEL],
                panels: end - p,
                first: p * PANEL,
                inp,
                out,
            }
        })
    }
}

/// Consecutive panels of packed weights and where their outputs go.
#[cfg(target_arch = "x86_64")]
struct Tile<'a> {
    panel: &'a [f32],
    bias: &'a [f32],
    /// Panels in this tile.
    panels: usize,
    /// The panel's first output.
    first: usize,
    inp: usize,
    out: usize,
}

#[cfg(target_arch = "x86_64")]
impl Tile<'_> {
    /// Every one of `n` rows through this tile's P panels, 12 rows at a time.
    #[target_feature(enable = "avx512f")]
    unsafe fn avx512_rows<const P: usize, const RELU: bool>(
        &self,
        n: usize,
        inputs: &[f32],
        outputs: &mut [f32],
    ) {
        let (inp, out) = (self.inp, self.out);
        for row in (0..n).step_by(12) {
            let (x, y) = (&inputs[row * inp..], &mut outputs[row * out..]);
            // SAFETY: the CPU has AVX-512F (this function's feature).
            unsafe {
                match n - row {
                    12.. => self.avx512::<12, P, RELU>(x, y),
                    11 => self.avx512::<11, P, RELU>(x, y),
                    10 => self.avx512::<10, P, RELU>(x, y),
                    9 => self.avx512::<9, P, RELU>(x, y),
                    8 => self.avx512::<8, P, RELU>(x, y),
                    7 => self.avx512::<7, P, RELU>(x, y),
                    6 => self.avx512::<6, P, RELU>(x, y),
                    5 => self.avx512::<5, P, RELU>(x, y),
                    4 => self.avx512::<4, P, RELU>(x, y),
                    3 => self.avx512::<3, P, RELU>(x, y),
                    2 => self.avx512::<2, P, RELU>(x, y),
                    _ => self.avx512::<1, P, RELU>(x, y),
                }
            }
        }
    }

    /// All of 1 to 3 rows through this tile's panels (up to 8 for 1 or 2 rows, 4 for 3).
    #[target_feature(enable = "avx512f")]
    unsafe fn avx512_few_rows<const RELU: bool>(&self, n: usize, x: &[f32], y: &mut [f32]) {
        // SAFETY: the CPU has AVX-512F (this function's feature).
        unsafe {
            match (n, self.panels) {
                (1, 8) => self.avx512::<1, 8, RELU>(x, y),
                (1, 7) => self.avx512::<1, 7, RELU>(x, y),
                (1, 6) => self.avx512::<1, 6, RELU>(x, y),
                (1, 5) => self.avx512::<1, 5, RELU>(x, y),
                (1, 4) => self.avx512::<1, 4, RELU>(x, y),
                (1, 3) => self.avx512::<1, 3, RELU>(x, y),
                (1, 2) => self.avx512::<1, 2, RELU>(x, y),
                (1, 1) => self.avx512::<1, 1, RELU>(x, y),
                (2, 8) => self.avx512::<2, 8, RELU>(x, y),
                (2, 7) => self.avx512::<2, 7, RELU>(x, y),
                (2, 6) => self.avx512::<2, 6, RELU>(x, y),
                (2, 5) => self.avx512::<2, 5, RELU>(x, y),
                (2, 4) => self.avx512::<2, 4, RELU>(x, y),
                (2, 3) => self.avx512::<2, 3, RELU>(x, y),
                (2, 2) => self.avx512::<2, 2, RELU>(x, y),
                (2, 1) => self.avx512::<2, 1, RELU>(x, y),
                (3, 4) => self.avx512::<3, 4, RELU>(x, y),
                (3, 3) => self.avx512::<3, 3, RELU>(x, y),
                (3, 2) => self.avx512::<3, 2, RELU>(x, y),
                (3, 1) => self.avx512::<3, 1, RELU>(x, y),
                _ => unreachable!("{n} rows through {} panels", self.panels),
            }
        }
    }

    /// R rows through P panels: `x` and `y` start at the first of the rows.
    #[target_feature(enable = "avx512f")]
    unsafe fn avx512<const R: usize, const P: usize, const RELU: bool>(
        &self,
        x: &[f32],
        y: &mut [f32],
    ) {
        use std::arch::x86_64::*;
        let (inp, out) = (self.inp, self.out);
        assert!(P == self.panels);
        assert!(self.panel.len() >= P * inp * PANEL && self.bias.len() >= P * PANEL);
        let last = self.first + (P - 1) * PANEL;
        assert!(x.len() >= R * inp && y.len() >= (R - 1) * out + last + PANEL.min(out - last));
        let (w, xs) = (self.panel.as_ptr(), x.as_ptr());
        // SAFETY: j < inp, q < P and r < R keep every read inside the lengths checked above.
        unsafe {
            let bias: [__m512; P] =
                std::array::from_fn(|q| _mm512_loadu_ps(self.bias.as_ptr().add(q * PANEL)));
            let mut acc = [bias; R];
            for j in 0..inp {
                let wv: [__m512; P] =
                    std::array::from_fn(|q| _mm512_loadu_ps(w.add((q * inp + j) * PANEL)));
                for (r, acc) in acc.iter_mut().enumerate() {
                    let xv = _mm512_set1_ps(*xs.add(r * inp + j));
                    for q in 0..P {
                        acc[q] = _mm512_fmadd_ps(wv[q], xv, acc[q]);
                    }
                }
            }
            // Masked stores write only the outputs that exist, with no copy through memory.
            let zero = _mm512_setzero_ps();
            for (r, acc) in acc.iter().enumerate() {
                for (q, &acc) in acc.iter().enumerate() {
                    // max(acc, 0) gives 0 for NaN and -0, as `relu` does.
                    let acc = if RELU { _mm512_max_ps(acc, zero) } else { acc };
                    let first = self.first + q * PANEL;
                    let width = PANEL.min(out - first);
                    let mask = (u32::MAX >> (32 - width)) as __mmask16;
                    _mm512_mask_storeu_ps(y.as_mut_ptr().add(r * out + first), mask, acc);
                }
            }
        }
    }
}

/// PyTorch's `nn.LayerNorm` over each row: the row standardised by its own mean and (biased)
/// variance plus `LAYER_NORM_EPS`, then scaled and shifted per feature.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct LayerNorm {
    scale: Vec<f32>,
    shift: Vec<f32>,
}

/// PyTorch's and burn's default epsilon of a layer norm.
pub(crate) const LAYER_NORM_EPS: f32 = 1e-5;

impl LayerNorm {
    /// A layer norm of `scale.len()` features; `shift` must be as long.
    pub(crate) fn new(scale: Vec<f32>, shift: Vec<f32>) -> Result<LayerNorm, LayerNormError> {
        if scale.len() != shift.len() {
            return Err(LayerNormError::ShiftLength {
                scale: scale.len(),
                shift: shift.len(),
            });
        }
        Ok(LayerNorm { scale, shift })
    }
    pub(crate) fn dim(&self) -> usize {
        self.scale.len()
    }
    pub(crate) fn scale(&self) -> &[f32] {
        &self.scale
    }
    pub(crate) fn shift(&self) -> &[f32] {
        &self.shift
    }

    /// Normalises every row of `rows` ([n, dim] row-major) in place.
    fn apply_rows(&self, rows: &mut [f32]) {
        let d = self.dim();
        for row in rows.chunks_exact_mut(d) {
            let mean = row.iter().sum::<f32>() / d as f32;
            let variance = row.iter().map(|v| (v - mean) * (v - mean)).sum::<f32>() / d as f32;
            let inv = 1.0 / (variance + LAYER_NORM_EPS).sqrt();
            for ((v, scale), shift) in row.iter_mut().zip(&self.scale).zip(&self.shift) {
                *v = (*v - mean) * inv * scale + shift;
            }
        }
    }
}

/// Layer norms that do not fit the chain they are given to.
#[derive(Debug, thiserror::Error)]
pub(crate) enum LayerNormError {
    #[error("a layer norm's shift has {shift} features, its scale {scale}")]
    ShiftLength { scale: usize, shift: usize },
    #[error("{got} layer norms for {expected} hidden layers; a chain has one per hidden layer")]
    Count { expected: usize, got: usize },
    #[error("layer norm {index} has {got} features but hidden layer {index} gives {expected}")]
    Width {
        index: usize,
        expected: usize,
        got: usize,
    },
}

/// A chain of dense layers. The activation follows every hidden layer, and the last layer too when
/// `activate_output` is set (SB3's `latent_pi` ends in an activation, critics do not). A chain
/// may normalise each hidden layer's output before its activation ([`Mlp::with_layer_norms`]).
#[derive(Clone, Debug)]
pub(crate) struct Mlp {
    input_dim: usize,
    layers: Vec<Dense>,
    activation: Activation,
    activate_output: bool,
    /// Empty, or one per hidden layer.
    norms: Vec<LayerNorm>,
}

/// Rows a large batch takes through the whole chain at a time: a block's two 256-wide
/// activations (64 KB each) and a 256x256 layer's weights (256 KB) fit a 512 KB L2 together.
const ROW_BLOCK: usize = 64;

/// Per-layer outputs of a forward, reused: hidden layers hold at most [`ROW_BLOCK`] rows, and the
/// last layer grows to the largest batch seen.
#[derive(Clone, Debug, Default)]
pub(crate) struct MlpScratch {
    outputs: Vec<Vec<f32>>,
}

/// A chain whose layer dimensions do not connect.
#[derive(Debug, thiserror::Error)]
#[error("layer {layer} takes {got} inputs but the previous layer gives {expected}")]
pub(crate) struct ShapeError {
    pub(crate) layer: usize,
    pub(crate) expected: usize,
    pub(crate) got: usize,
}

/// Sets `buffer` to `len` values, allocating only when it has never been that long.
pub(crate) fn resize(buffer: &mut Vec<f32>, len: usize) {
    buffer.resize(len, 0.0);
}

impl Mlp {
    pub(crate) fn new(
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
            norms: Vec::new(),
        })
    }

    /// The chain with a layer norm after each hidden layer, before its activation (the
    /// `Linear, LayerNorm, ReLU` blocks of layer-normalised critics).
    pub(crate) fn with_layer_norms(mut self, norms: Vec<LayerNorm>) -> Result<Mlp, LayerNormError> {
        let hidden = self.layers.len().saturating_sub(1);
        if norms.len() != hidden {
            return Err(LayerNormError::Count {
                expected: hidden,
                got: norms.len(),
            });
        }
        for (index, (norm, dense)) in norms.iter().zip(&self.layers).enumerate() {
            if norm.dim() != dense.output_dim() {
                return Err(LayerNormError::Width {
                    index,
                    expected: dense.output_dim(),
                    got: norm.dim(),
                });
            }
        }
        self.norms = norms;
        Ok(self)
    }

    /// The hidden layers' norms (empty when the chain has none).
    pub(crate) fn norms(&self) -> &[LayerNorm] {
        &self.norms
    }
    #[cfg(feature = "onnx")]
    pub(crate) fn activation(&self) -> Activation {
        self.activation
    }
    /// Whether the last layer is activated too.
    #[cfg(feature = "onnx")]
    pub(crate) fn activates_output(&self) -> bool {
        self.activate_output
    }

    pub(crate) fn input_dim(&self) -> usize {
        self.input_dim
    }
    pub(crate) fn output_dim(&self) -> usize {
        self.layers.last().map_or(self.input_dim, Dense::output_dim)
    }
    pub(crate) fn layers(&self) -> &[Dense] {
        &self.layers
    }
    /// Floating-point operations of one state's forward (multiply-adds count as two).
    pub(crate) fn flops(&self) -> u64 {
        self.layers.iter().map(Dense::flops).sum()
    }

    pub(crate) fn scratch(&self) -> MlpScratch {
        self.scratch_for(1)
    }

    /// Scratch with room for batches of up to `rows` states.
    pub(crate) fn scratch_for(&self, rows: usize) -> MlpScratch {
        MlpScratch {
            outputs: self
                .layers
                .iter()
                .enumerate()
                .map(|(i, d)| Vec::with_capacity(self.rows_held(i, rows) * d.output_dim()))
                .collect(),
        }
    }

    /// Rows layer `i`'s buffer holds for a batch of `n`: hidden layers one row block, the last
    /// layer every row.
    fn rows_held(&self, i: usize, n: usize) -> usize {
        if i + 1 == self.layers.len() {
            n
        } else {
            n.min(ROW_BLOCK)
        }
    }

    /// Forward of n states: `inputs` is [n, input_dim] row-major; the result ([n, output_dim])
    /// lives in `scratch`. Allocates only when n exceeds every earlier batch.
    ///
    /// A large batch goes through the whole chain in blocks of [`ROW_BLOCK`] rows, so a block's
    /// hidden activations stay in L2 between layers instead of streaming the batch's from L3 once
    /// per panel of outputs. Rows are independent, so the bits do not depend on the blocking.
    pub(crate) fn forward_rows<'s>(
        &self,
        inputs: &'s [f32],
        scratch: &'s mut MlpScratch,
    ) -> &'s [f32] {
        assert_eq!(
            inputs.len() % self.input_dim,
            0,
            "Mlp::forward_rows input length"
        );
        let n = inputs.len() / self.input_dim;
        let Some(last) = self.layers.len().checked_sub(1) else {
            return inputs;
        };
        scratch.outputs.resize_with(self.layers.len(), Vec::new);
        let out_dim = self.layers[last].output_dim();
        // Buffers only grow: a smaller batch uses their start, so batch sizes that come and go
        // cost no refilling.
        for (i, dense) in self.layers.iter().enumerate() {
            let len = self.rows_held(i, n) * dense.output_dim();
            if scratch.outputs[i].len() < len {
                scratch.outputs[i].resize(len, 0.0);
            }
        }
        let mut start = 0;
        while start < n {
            let rows = ROW_BLOCK.min(n - start);
            let x = &inputs[start * self.input_dim..(start + rows) * self.input_dim];
            self.forward_block(x, start, rows, &mut scratch.outputs);
            start += rows;
        }
        &scratch.outputs[last][..n * out_dim]
    }

    /// Rows `start..start + rows` of a batch through every layer: hidden outputs at the start of
    /// their buffers, the last layer's at the rows' place in its buffer.
    fn forward_block(&self, inputs: &[f32], start: usize, rows: usize, outputs: &mut [Vec<f32>]) {
        let last = self.layers.len() - 1;
        for (i, dense) in self.layers.iter().enumerate() {
            let (before, rest) = outputs.split_at_mut(i);
            let width = dense.output_dim();
            let out = match i == last {
                true => &mut rest[0][start * width..(start + rows) * width],
                false => &mut rest[0][..rows * width],
            };
            let x = match i {
                0 => inputs,
                _ => &before[i - 1][..rows * dense.input_dim()],
            };
            let activate = i < last || self.activate_output;
            match self.norms.get(i) {
                // ReLU straight after the layer goes into the kernel's store.
                None if activate && self.activation == Activation::Relu => {
                    dense.forward_rows_relu(x, out)
                }
                norm => {
                    dense.forward_rows(x, out);
                    if let Some(norm) = norm {
                        norm.apply_rows(out);
                    }
                    if activate {
                        self.activation.apply(out);
                    }
                }
            }
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
    fn layer_norms_standardise_each_hidden_row_before_its_activation() {
        let norm = |d: usize, seed: f32| {
            let scale = (0..d)
                .map(|i| 0.5 + ((i as f32 + seed) * 0.7).sin())
                .collect();
            let shift = (0..d).map(|i| ((i as f32 - seed) * 0.3).cos()).collect();
            LayerNorm::new(scale, shift).unwrap()
        };
        let mlp = chain()
            .with_layer_norms(vec![norm(7, 1.0), norm(6, 2.0)])
            .unwrap();
        // PyTorch's Linear -> LayerNorm -> ReLU blocks, in f64.
        let reference = |x: &[f32]| -> Vec<f64> {
            let mut v: Vec<f64> = x.iter().map(|&a| f64::from(a)).collect();
            for (i, d) in mlp.layers().iter().enumerate() {
                let mut out: Vec<f64> = (0..d.output_dim())
                    .map(|r| {
                        f64::from(d.bias[r])
                            + (0..d.input_dim())
                                .map(|c| f64::from(d.weight[(r, c)]) * v[c])
                                .sum::<f64>()
                    })
                    .collect();
                if let Some(n) = mlp.norms().get(i) {
                    let mean = out.iter().sum::<f64>() / out.len() as f64;
                    let var =
                        out.iter().map(|o| (o - mean).powi(2)).sum::<f64>() / out.len() as f64;
                    for (k, o) in out.iter_mut().enumerate() {
                        let standard = (*o - mean) / (var + f64::from(LAYER_NORM_EPS)).sqrt();
                        *o = standard * f64::from(n.scale()[k]) + f64::from(n.shift()[k]);
                        *o = o.max(0.0);
                    }
                }
                v = out;
            }
            v
        };
        let rows: Vec<f32> = (0..3 * 5)
            .map(|i| ((i as f32) * 0.91).sin() * 2.0)
            .collect();
        let mut scratch = mlp.scratch_for(3);
        let out = mlp.forward_rows(&rows, &mut scratch).to_vec();
        for (r, x) in rows.chunks(5).enumerate() {
            for (k, want) in reference(x).iter().enumerate() {
                let got = f64::from(out[2 * r + k]);
                assert!(
                    (got - want).abs() < 1e-4,
                    "row {r} output {k}: {got} against {want}"
                );
            }
        }
        // Without the norms the same chain gives something else.
        let plain = chain()
            .forward_rows(&rows, &mut chain().scratch_for(3))
            .to_vec();
        assert!(plain.iter().zip(&out).any(|(a, b)| (a - b).abs() > 1e-3));
    }

    #[test]
    fn layer_norms_that_do_not_fit_are_rejected() {
        let ones = |d: usize| LayerNorm::new(vec![1.0; d], vec![0.0; d]).unwrap();
        let err = chain().with_layer_norms(vec![ones(7)]).unwrap_err();
        assert!(
            err.to_string()
                .contains("1 layer norms for 2 hidden layers"),
            "{err}"
        );
        let err = chain()
            .with_layer_norms(vec![ones(7), ones(5)])
            .unwrap_err();
        assert!(
            err.to_string().contains("layer norm 1 has 5 features"),
            "{err}"
        );
        let err = LayerNorm::new(vec![1.0; 3], vec![0.0; 2]).unwrap_err();
        assert!(err.to_string().contains("shift has 2 features"), "{err}");
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
        // 150 states: two full row blocks of the chain and a partial one, each of full and
        // partial register tiles; some inputs exactly zero.
        let states: Vec<Vec<f32>> = (0..150)
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
    fn a_batch_of_no_rows_computes_nothing() {
        let d = layer(37, 23, 4.0);
        let mut none: Vec<f32> = Vec::new();
        d.forward_rows(&[], &mut none);
        d.forward_rows_relu(&[], &mut none);
        #[cfg(target_arch = "x86_64")]
        if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
            // SAFETY: the CPU has the features.
            unsafe { d.forward_avx2::<true>(&[], &mut none) };
        }
        assert!(none.is_empty());
    }

    #[test]
    fn every_kernel_gives_the_scalar_bits() {
        // Partial panels (37 = 16 + 16 + 5 outputs: a two-panel tile, then a lone partial panel;
        // 53 = 16 + 16 + 16 + 5: a partial panel inside a two-panel tile), every tile height,
        // one input; with and without the fused ReLU, and a NaN input in the first row.
        let bits = |v: &[f32]| v.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        // Few rows take wide tiles: 133 = 8 x 16 + 5 (a full 8-panel tile, then a partial
        // panel alone), 100 = 6 x 16 + 4 (a 7-panel tile ending in a partial panel). Heads of 1
        // and 6 outputs take one AVX2 vector by up to 12 rows; 8, 9 and 11 rows split evenly.
        // Heads of 1-4 outputs put 8 rows in the lanes: inputs in whole transposes (256), with
        // a tail (13) or only a tail (5), then the rows left over through the tiles.
        for (out, inp) in [
            (37, 23),
            (53, 7),
            (16, 1),
            (5, 256),
            (256, 18),
            (133, 11),
            (100, 9),
            (1, 256),
            (6, 256),
            (64, 64),
            (2, 256),
            (3, 13),
            (4, 5),
        ] {
            let d = layer(out, inp, 5.0);
            for n in [1, 2, 3, 4, 5, 6, 7, 8, 9, 11, 12, 13, 16, 25, 64] {
                let mut x: Vec<f32> = (0..n * inp).map(|i| (i as f32 * 0.29).sin()).collect();
                x[inp - 1] = f32::NAN;
                let mut plain = vec![0.0; n * out];
                d.forward_scalar::<false>(&x, &mut plain);
                let mut rectified = vec![0.0; n * out];
                d.forward_scalar::<true>(&x, &mut rectified);
                let mut unfused = plain.clone();
                Activation::Relu.apply(&mut unfused);
                assert_eq!(bits(&rectified), bits(&unfused), "{out}x{inp}, {n} rows");
                assert!(rectified[..out].iter().all(|&v| v == 0.0));
                let mut got = vec![f32::NAN; n * out];
                d.forward_rows(&x, &mut got);
                assert_eq!(bits(&got), bits(&plain), "{out}x{inp}, {n} rows");
                d.forward_rows_relu(&x, &mut got);
                assert_eq!(bits(&got), bits(&rectified), "relu {out}x{inp}, {n} rows");
                #[cfg(target_arch = "x86_64")]
                if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
                    got.fill(f32::NAN);
                    // SAFETY: the CPU has the features.
                    unsafe { d.forward_avx2::<false>(&x, &mut got) };
                    assert_eq!(bits(&got), bits(&plain), "avx2 {out}x{inp}, {n} rows");
                    // SAFETY: as above.
                    unsafe { d.forward_avx2::<true>(&x, &mut got) };
                    assert_eq!(
                        bits(&got),
                        bits(&rectified),
                        "avx2 relu {out}x{inp}, {n} rows"
                    );
                }
            }
        }
    }

    #[test]
    fn scratch_stops_allocating_once_grown() {
        let mlp = chain();
        let mut scratch = mlp.scratch();
        // 150 rows take three row blocks; 3 and 16 fewer than one.
        mlp.forward_rows(&[0.5; 5 * 150], &mut scratch);
        let pointers: Vec<*const f32> = scratch.outputs.iter().map(|o| o.as_ptr()).collect();
        mlp.forward_rows(&[0.5; 5 * 3], &mut scratch);
        mlp.forward_rows(&[0.5; 5 * 16], &mut scratch);
        mlp.forward_rows(&[0.5; 5 * 150], &mut scratch);
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
