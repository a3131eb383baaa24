//! Networks with hand-written backward passes over [`super::mat`]:
//! - [`GaussianActor`]: MLP `obs -> hidden (ELU) -> action mean`, plus a learned
//!   state-independent log-std.
//! - [`IqnCritic`]: `Z_tau(s) = head(phi(s) * psi(tau))` (IQN, Dabney et al. 2018).
//! - [`ScalarCritic`]: MLP `obs -> hidden (ELU) -> V(s)` (risk-neutral baseline).
//!
//! Every network keeps its parameters in one flat [`ParamSet`] (named views for
//! checkpoints, flat slices for Adam and the global gradient norm). Shapes are
//! row-major; a batch of `b` inputs is a `b x dim` slice. Linear weights are
//! stored `in x out` so that `y = x W + b`.

use super::layout::gather_columns;
use super::mat::{add_col_sums, elu_backward_inplace, elu_inplace, fill_rows, gemm, relu_inplace};
use rand::Rng;
use std::ops::Range;

/// One named tensor inside a [`ParamSet`].
#[derive(Clone, Debug, PartialEq)]
pub struct ParamEntry {
    /// e.g. `"l0.weight"` (the owner adds its own prefix in checkpoints).
    pub name: String,
    pub shape: Vec<usize>,
    /// Offset in [`ParamSet::data`].
    pub offset: usize,
}

impl ParamEntry {
    pub fn len(&self) -> usize {
        self.shape.iter().product()
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// All parameters of one network in a single flat vector.
#[derive(Clone, Debug, Default)]
pub struct ParamSet {
    pub data: Vec<f32>,
    pub entries: Vec<ParamEntry>,
}

impl ParamSet {
    /// Append a tensor filled by `init`; returns its offset.
    fn add(&mut self, name: &str, shape: &[usize], mut init: impl FnMut() -> f32) -> usize {
        let offset = self.data.len();
        let n: usize = shape.iter().product();
        self.data.extend((0..n).map(|_| init()));
        self.entries.push(ParamEntry {
            name: name.to_string(),
            shape: shape.to_vec(),
            offset,
        });
        offset
    }

    /// PyTorch's default `nn.Linear` init (what rsl_rl uses): W, b ~ U(+-1/sqrt(in)).
    fn add_linear(&mut self, name: &str, inp: usize, out: usize, rng: &mut impl Rng) -> Linear {
        let bound = 1.0 / (inp as f32).sqrt();
        let w = self.add(&format!("{name}.weight"), &[inp, out], || {
            rng.gen_range(-bound..bound)
        });
        let b = self.add(&format!("{name}.bias"), &[out], || {
            rng.gen_range(-bound..bound)
        });
        Linear { w, b, inp, out }
    }

    pub fn len(&self) -> usize {
        self.data.len()
    }
    pub fn is_empty(&self) -> bool {
        self.data.is_empty()
    }
}

/// Offsets of one affine layer `y[b x out] = x[b x inp] W[inp x out] + bias[out]`.
#[derive(Clone, Copy, Debug)]
struct Linear {
    w: usize,
    b: usize,
    inp: usize,
    out: usize,
}

impl Linear {
    /// `y = x W + b` (y is resized to `batch x out`).
    fn forward(&self, p: &[f32], x: &[f32], batch: usize, y: &mut Vec<f32>) {
        y.resize(batch * self.out, 0.0);
        fill_rows(y, &p[self.b..self.b + self.out]);
        let w = &p[self.w..self.w + self.inp * self.out];
        gemm(batch, self.out, self.inp, x, false, w, false, y, true);
    }

    /// Accumulates dW, db into `g` from `dy` (`batch x out`).
    fn backward_params(&self, g: &mut [f32], x: &[f32], batch: usize, dy: &[f32]) {
        let (inp, out) = (self.inp, self.out);
        gemm(
            inp,
            out,
            batch,
            x,
            true,
            dy,
            false,
            &mut g[self.w..self.w + inp * out],
            true,
        );
        add_col_sums(dy, &mut g[self.b..self.b + out]);
    }

    /// `dx = dy W^T` (`dx` is resized to `batch x inp`).
    fn backward_input(&self, p: &[f32], batch: usize, dy: &[f32], dx: &mut Vec<f32>) {
        let (inp, out) = (self.inp, self.out);
        dx.resize(batch * inp, 0.0);
        gemm(
            batch,
            inp,
            out,
            dy,
            false,
            &p[self.w..self.w + inp * out],
            true,
            dx,
            false,
        );
    }
}

/// A multilayer perceptron with ELU between layers.
#[derive(Clone, Debug)]
pub struct Mlp {
    layers: Vec<Linear>,
    /// ELU after the last layer too (the IQN trunk phi(s)); otherwise linear output.
    activate_last: bool,
}

/// Per-layer outputs of an [`Mlp`] forward pass, kept for the backward pass,
/// and the backward pass's scratch: reused, so steady-state passes allocate nothing.
#[derive(Clone, Debug, Default)]
pub struct MlpCache {
    acts: Vec<Vec<f32>>,
    /// `d loss / d input` of each layer (`batch x in`): one buffer per layer, so
    /// each keeps its size from pass to pass (one buffer swapped between layers of
    /// different widths was zero-filled on every growth).
    grads: Vec<Vec<f32>>,
    /// The network's input when it reads a subset of the observation row.
    input: Vec<f32>,
    /// Latent module (encoder or adaptation): its input and its own cache.
    latent_input: Vec<f32>,
    latent: Vec<MlpCache>,
}

impl MlpCache {
    /// Output of the last layer (`batch x out_dim`).
    pub fn output(&self) -> &[f32] {
        self.acts.last().map(|a| a.as_slice()).unwrap_or(&[])
    }
}

impl Mlp {
    /// `dims = [in, h1, ..., out]`; parameters named `{prefix}l{i}.weight|bias`.
    fn build(
        ps: &mut ParamSet,
        prefix: &str,
        dims: &[usize],
        activate_last: bool,
        rng: &mut impl Rng,
    ) -> Self {
        let layers = dims
            .windows(2)
            .enumerate()
            .map(|(i, d)| ps.add_linear(&format!("{prefix}l{i}"), d[0], d[1], rng))
            .collect();
        Mlp {
            layers,
            activate_last,
        }
    }

    pub fn out_dim(&self) -> usize {
        self.layers.last().map_or(0, |l| l.out)
    }

    fn activated(&self, l: usize) -> bool {
        l + 1 < self.layers.len() || self.activate_last
    }

    /// Forward pass of `x` (`batch x in`); the output is `cache.output()`.
    pub fn forward(&self, p: &[f32], x: &[f32], batch: usize, cache: &mut MlpCache) {
        cache.acts.resize_with(self.layers.len(), Vec::new);
        for (l, layer) in self.layers.iter().enumerate() {
            let (prev, rest) = cache.acts.split_at_mut(l);
            let input = if l == 0 { x } else { &prev[l - 1] };
            layer.forward(p, input, batch, &mut rest[0]);
            if self.activated(l) {
                elu_inplace(&mut rest[0]);
            }
        }
    }

    /// Backward pass from `dout` (`batch x out`), accumulating parameter
    /// gradients into `g`. `dout` is used as scratch; with `want_dx` it holds
    /// d/dx (`batch x in`) on return.
    #[allow(clippy::too_many_arguments)]
    pub fn backward(
        &self,
        p: &[f32],
        g: &mut [f32],
        x: &[f32],
        batch: usize,
        cache: &mut MlpCache,
        dout: &mut Vec<f32>,
        want_dx: bool,
    ) {
        let Some(last) = self.layers.len().checked_sub(1) else {
            return;
        };
        let MlpCache { acts, grads, .. } = cache;
        grads.resize_with(self.layers.len(), Vec::new);
        for (l, layer) in self.layers.iter().enumerate().rev() {
            // d loss / d output of layer l: the caller's for the last layer, else
            // the input gradient of layer l + 1
            let (below, above) = grads.split_at_mut(l + 1);
            let dy = if l == last { &mut *dout } else { &mut above[0] };
            if self.activated(l) {
                elu_backward_inplace(dy, &acts[l]);
            }
            let input = if l == 0 { x } else { &acts[l - 1] };
            layer.backward_params(g, input, batch, dy);
            if l > 0 || want_dx {
                layer.backward_input(p, batch, dy, &mut below[l]);
            }
        }
        if want_dx {
            dout.clear();
            dout.extend_from_slice(&grads[0]);
        }
    }
}

/// Which columns of the observation row a network reads (concatenated in order).
#[derive(Clone, Debug, PartialEq)]
pub struct InputSel {
    pub ranges: Vec<Range<usize>>,
    pub row_width: usize,
}

impl InputSel {
    /// The whole row.
    pub fn all(width: usize) -> InputSel {
        InputSel {
            ranges: std::iter::once(0..width).collect(),
            row_width: width,
        }
    }
    pub fn width(&self) -> usize {
        self.ranges.iter().map(|r| r.len()).sum()
    }
    fn is_identity(&self) -> bool {
        self.ranges.len() == 1 && self.ranges[0] == (0..self.row_width)
    }
    /// The selected columns of `obs`: `obs` itself, or a copy gathered into `buf`.
    fn select<'a>(&self, obs: &'a [f32], buf: &'a mut Vec<f32>) -> &'a [f32] {
        if self.is_identity() {
            obs
        } else {
            gather_columns(obs, self.row_width, &self.ranges, buf);
            buf
        }
    }
}

/// Where the actor's latent `z` comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LatentSource {
    /// `z = encoder(privileged)`: RMA's teacher (trained with the policy by PPO).
    Encoder,
    /// `z = adaptation(history)`: RMA's student (trained by regression on z).
    Adaptation,
}

/// A latent input of the actor: an MLP over some columns, appended to the
/// actor's direct inputs.
#[derive(Clone, Debug)]
pub struct LatentModule {
    pub mlp: Mlp,
    pub input: InputSel,
}

/// Gaussian policy: `mean = MLP(obs)`, `std = exp(log_std)` (state independent).
#[derive(Clone, Debug)]
pub struct GaussianActor {
    pub params: ParamSet,
    mlp: Mlp,
    log_std: usize,
    /// Width of the observation row (all groups).
    pub obs_dim: usize,
    pub act_dim: usize,
    /// Columns read directly; a latent, when present, is appended after them.
    input: InputSel,
    encoder: Option<LatentModule>,
    adaptation: Option<LatentModule>,
    latent_source: LatentSource,
    latent_dim: usize,
}

impl GaussianActor {
    /// `hidden`: e.g. `[512, 256, 128]`; `init_std`: initial action std (rsl_rl: 1.0).
    pub fn new(
        obs_dim: usize,
        act_dim: usize,
        hidden: &[usize],
        init_std: f32,
        rng: &mut impl Rng,
    ) -> Self {
        GaussianActor::with_inputs(InputSel::all(obs_dim), 0, act_dim, hidden, init_std, rng)
    }

    /// An actor reading `input` columns plus a `latent_dim` latent (added with
    /// [`GaussianActor::add_encoder`]; 0 for none).
    pub fn with_inputs(
        input: InputSel,
        latent_dim: usize,
        act_dim: usize,
        hidden: &[usize],
        init_std: f32,
        rng: &mut impl Rng,
    ) -> Self {
        let mut params = ParamSet::default();
        let dims: Vec<usize> = [&[input.width() + latent_dim][..], hidden, &[act_dim]].concat();
        let mlp = Mlp::build(&mut params, "", &dims, false, rng);
        let log_std = params.add("log_std", &[act_dim], || init_std.ln());
        GaussianActor {
            params,
            mlp,
            log_std,
            obs_dim: input.row_width,
            act_dim,
            input,
            encoder: None,
            adaptation: None,
            latent_source: LatentSource::Encoder,
            latent_dim,
        }
    }

    /// Adds RMA's encoder `z = MLP(input)` (`hidden`, ELU, linear output of
    /// `latent_dim` values; parameters `enc.*`), feeding the actor.
    pub fn add_encoder(&mut self, input: InputSel, hidden: &[usize], rng: &mut impl Rng) {
        let dims: Vec<usize> = [&[input.width()][..], hidden, &[self.latent_dim]].concat();
        let mlp = Mlp::build(&mut self.params, "enc.", &dims, false, rng);
        self.encoder = Some(LatentModule { mlp, input });
    }

    /// Adds RMA's adaptation module `z_hat = MLP(input)` (parameters `adapt.*`).
    pub fn add_adaptation(&mut self, input: InputSel, hidden: &[usize], rng: &mut impl Rng) {
        let dims: Vec<usize> = [&[input.width()][..], hidden, &[self.latent_dim]].concat();
        let mlp = Mlp::build(&mut self.params, "adapt.", &dims, false, rng);
        self.adaptation = Some(LatentModule { mlp, input });
    }

    pub fn latent_dim(&self) -> usize {
        self.latent_dim
    }
    pub fn latent_source(&self) -> LatentSource {
        self.latent_source
    }
    /// Which module feeds `z` from now on (the student uses the adaptation module).
    pub fn set_latent_source(&mut self, source: LatentSource) {
        self.latent_source = source;
    }
    pub fn encoder(&self) -> Option<&LatentModule> {
        self.encoder.as_ref()
    }
    pub fn adaptation(&self) -> Option<&LatentModule> {
        self.adaptation.as_ref()
    }
    /// Columns the actor reads directly.
    pub fn direct_input(&self) -> &InputSel {
        &self.input
    }
    /// The base policy MLP (input: direct columns then z).
    pub fn base_mlp(&self) -> &Mlp {
        &self.mlp
    }

    /// Multiplies the base policy's output layer (weights and bias) by `factor`:
    /// with a small factor the first actions sit near 0, the default pose
    /// (Andrychowicz et al. 2021, "What matters in on-policy RL", recommend 0.01).
    pub fn scale_output_layer(&mut self, factor: f32) {
        let last = self.mlp.layers.last().expect("the policy MLP has layers");
        let weights = last.w..last.w + last.inp * last.out;
        let bias = last.b..last.b + last.out;
        for range in [weights, bias] {
            self.params.data[range]
                .iter_mut()
                .for_each(|p| *p *= factor);
        }
    }

    fn latent_module(&self) -> Option<&LatentModule> {
        match self.latent_source {
            LatentSource::Encoder => self.encoder.as_ref(),
            LatentSource::Adaptation => self.adaptation.as_ref(),
        }
    }

    /// `z` of `module` for `batch` rows of `obs` (`batch x latent_dim`).
    pub fn latent_of(&self, module: &LatentModule, obs: &[f32], batch: usize) -> Vec<f32> {
        let mut cache = MlpCache::default();
        let mut buf = Vec::new();
        let x = module.input.select(obs, &mut buf);
        module.mlp.forward(&self.params.data, x, batch, &mut cache);
        cache.acts.pop().unwrap_or_default()
    }

    /// Log standard deviation per action dimension (`act_dim`).
    pub fn log_std(&self) -> &[f32] {
        &self.params.data[self.log_std..self.log_std + self.act_dim]
    }

    /// Offset of the log-std in the flat parameter (and gradient) vector.
    pub fn log_std_offset(&self) -> usize {
        self.log_std
    }

    /// Action means for `batch` observations, kept in `cache` (`batch x act_dim`).
    pub fn forward(&self, obs: &[f32], batch: usize, cache: &mut MlpCache) {
        let p = &self.params.data;
        let mut input = std::mem::take(&mut cache.input);
        match self.latent_module() {
            None if self.latent_dim == 0 => {
                let x = self.input.select(obs, &mut input);
                self.mlp.forward(p, x, batch, cache);
            }
            module => {
                let mut zin = std::mem::take(&mut cache.latent_input);
                cache.latent.resize_with(1, MlpCache::default);
                let z: &[f32] = match module {
                    Some(m) => {
                        gather_columns(obs, m.input.row_width, &m.input.ranges, &mut zin);
                        m.mlp.forward(p, &zin, batch, &mut cache.latent[0]);
                        cache.latent[0].output()
                    }
                    None => &[],
                };
                // x = [direct columns | z] per row (z = 0 without a module)
                let (dw, lw) = (self.input.width(), self.latent_dim);
                input.clear();
                input.reserve(batch * (dw + lw));
                for (b, row) in obs.chunks_exact(self.obs_dim).enumerate() {
                    for r in &self.input.ranges {
                        input.extend_from_slice(&row[r.clone()]);
                    }
                    match z.get(b * lw..(b + 1) * lw) {
                        Some(zr) => input.extend_from_slice(zr),
                        None => input.extend(std::iter::repeat_n(0.0, lw)),
                    }
                }
                self.mlp.forward(p, &input, batch, cache);
                cache.latent_input = zin;
            }
        }
        cache.input = input;
    }

    /// Inference: action means (`batch x act_dim`).
    pub fn mean(&self, obs: &[f32], batch: usize) -> Vec<f32> {
        let mut cache = MlpCache::default();
        self.forward(obs, batch, &mut cache);
        cache.acts.pop().unwrap_or_default()
    }

    /// Accumulate parameter gradients from d loss / d mean (`batch x act_dim`,
    /// overwritten as scratch). (The log-std gradient is added by the caller at
    /// `log_std_offset()`.)
    pub fn backward(
        &self,
        grads: &mut [f32],
        obs: &[f32],
        batch: usize,
        cache: &mut MlpCache,
        d_mean: &mut Vec<f32>,
    ) {
        let p = &self.params.data;
        let input = std::mem::take(&mut cache.input);
        let x = if self.latent_dim == 0 && self.input.is_identity() {
            obs
        } else {
            &input
        };
        // the encoder learns with the policy (RMA phase 1); the adaptation
        // module learns only by regression (phase 2), never here
        let train_encoder = self.latent_source == LatentSource::Encoder && self.encoder.is_some();
        self.mlp
            .backward(p, grads, x, batch, cache, d_mean, train_encoder);
        if let (true, Some(enc)) = (train_encoder, &self.encoder) {
            let (dw, lw) = (self.input.width(), self.latent_dim);
            let mut dz = Vec::with_capacity(batch * lw);
            for row in d_mean.chunks_exact(dw + lw) {
                dz.extend_from_slice(&row[dw..]);
            }
            let zin = std::mem::take(&mut cache.latent_input);
            enc.mlp
                .backward(p, grads, &zin, batch, &mut cache.latent[0], &mut dz, false);
            cache.latent_input = zin;
        }
        cache.input = input;
    }
}

/// Scalar value critic `V(s)`.
#[derive(Clone, Debug)]
pub struct ScalarCritic {
    pub params: ParamSet,
    mlp: Mlp,
    input: InputSel,
}

impl ScalarCritic {
    pub fn new(obs_dim: usize, hidden: &[usize], rng: &mut impl Rng) -> Self {
        ScalarCritic::with_input(InputSel::all(obs_dim), hidden, rng)
    }

    /// A critic reading the `input` columns of the observation row.
    pub fn with_input(input: InputSel, hidden: &[usize], rng: &mut impl Rng) -> Self {
        let mut params = ParamSet::default();
        let dims: Vec<usize> = [&[input.width()][..], hidden, &[1]].concat();
        let mlp = Mlp::build(&mut params, "", &dims, false, rng);
        ScalarCritic { params, mlp, input }
    }

    /// Values (`batch`), kept in `cache`.
    pub fn forward(&self, obs: &[f32], batch: usize, cache: &mut MlpCache) {
        let mut input = std::mem::take(&mut cache.input);
        let x = self.input.select(obs, &mut input);
        self.mlp.forward(&self.params.data, x, batch, cache);
        cache.input = input;
    }

    /// Inference: `V(s)` for `batch` observations.
    pub fn values(&self, obs: &[f32], batch: usize) -> Vec<f32> {
        let mut cache = MlpCache::default();
        self.forward(obs, batch, &mut cache);
        cache.acts.pop().unwrap_or_default()
    }

    /// Accumulate gradients from d loss / d V (`batch`, overwritten as scratch).
    pub fn backward(
        &self,
        grads: &mut [f32],
        obs: &[f32],
        batch: usize,
        cache: &mut MlpCache,
        dv: &mut Vec<f32>,
    ) {
        let input = std::mem::take(&mut cache.input);
        let x = if self.input.is_identity() {
            obs
        } else {
            &input
        };
        self.mlp
            .backward(&self.params.data, grads, x, batch, cache, dv, false);
        cache.input = input;
    }
}

/// IQN state-value critic. `phi(s)`: trunk MLP with ELU after every layer
/// (`[obs, h1, .., hL]`); `psi(tau) = ReLU(W cos(pi i tau) + b)`, `i = 0..num_cos`;
/// `Z_tau(s) = w . (phi(s) * psi(tau)) + c`. The merge sits at the last hidden
/// layer (about 20x cheaper than after the first), so with taus shared by a batch the head is one
/// GEMM: `Z = phi(s) [b x F] . (psi * w)^T [F x N]`.
#[derive(Clone, Debug)]
pub struct IqnCritic {
    pub params: ParamSet,
    input: InputSel,
    trunk: Mlp,
    embed: Linear,
    head_w: usize,
    head_b: usize,
    num_cos: usize,
    feat: usize,
}

/// Forward-pass intermediates of [`IqnCritic`] for its backward pass.
#[derive(Clone, Debug, Default)]
pub struct IqnCache {
    trunk: MlpCache,
    /// `N x num_cos` cosine features.
    cos: Vec<f32>,
    /// `N x F` psi(tau) (after ReLU).
    emb: Vec<f32>,
    /// `N x F` psi(tau) * w.
    g: Vec<f32>,
    /// `batch x N` output `Z`.
    z: Vec<f32>,
    /// Backward scratch: `batch x F` d phi, `N x F` d g.
    dphi: Vec<f32>,
    dg: Vec<f32>,
}

impl IqnCache {
    /// `Z` of the last forward pass (`batch x N`).
    pub fn output(&self) -> &[f32] {
        &self.z
    }
}

impl IqnCritic {
    /// `hidden`: trunk sizes (e.g. `[512, 256, 128]`); `num_cos`: cosine basis size (64).
    pub fn new(obs_dim: usize, hidden: &[usize], num_cos: usize, rng: &mut impl Rng) -> Self {
        IqnCritic::with_input(InputSel::all(obs_dim), hidden, num_cos, rng)
    }

    /// A critic reading the `input` columns of the observation row.
    pub fn with_input(
        input: InputSel,
        hidden: &[usize],
        num_cos: usize,
        rng: &mut impl Rng,
    ) -> Self {
        let obs_dim = input.width();
        assert!(
            !hidden.is_empty(),
            "IQN critic needs at least one hidden layer"
        );
        let mut params = ParamSet::default();
        let dims: Vec<usize> = [&[obs_dim][..], hidden].concat();
        let trunk = Mlp::build(&mut params, "trunk.", &dims, true, rng);
        let feat = trunk.out_dim();
        let embed = params.add_linear("tau_embed", num_cos, feat, rng);
        let head = params.add_linear("head", feat, 1, rng);
        IqnCritic {
            params,
            input,
            trunk,
            embed,
            head_w: head.w,
            head_b: head.b,
            num_cos,
            feat,
        }
    }

    /// `Z_tau(s)` for every observation and tau: returns `batch x taus.len()`
    /// (kept in `cache`).
    pub fn forward<'c>(
        &self,
        obs: &[f32],
        batch: usize,
        taus: &[f32],
        cache: &'c mut IqnCache,
    ) -> &'c [f32] {
        let p = &self.params.data;
        let (n, f) = (taus.len(), self.feat);
        let mut input = std::mem::take(&mut cache.trunk.input);
        let x = self.input.select(obs, &mut input);
        self.trunk.forward(p, x, batch, &mut cache.trunk);
        cache.trunk.input = input;
        cache.cos.clear();
        for &t in taus {
            cache
                .cos
                .extend((0..self.num_cos).map(|i| (std::f32::consts::PI * i as f32 * t).cos()));
        }
        self.embed.forward(p, &cache.cos, n, &mut cache.emb);
        relu_inplace(&mut cache.emb);
        let w = &p[self.head_w..self.head_w + f];
        cache.g.clear();
        for row in cache.emb.chunks_exact(f) {
            cache.g.extend(row.iter().zip(w).map(|(e, w)| e * w));
        }
        cache.z.clear();
        cache.z.resize(batch * n, p[self.head_b]);
        gemm(
            batch,
            n,
            f,
            cache.trunk.output(),
            false,
            &cache.g,
            true,
            &mut cache.z,
            true,
        );
        &cache.z
    }

    /// Inference: `batch x taus.len()` quantiles.
    pub fn quantiles(&self, obs: &[f32], batch: usize, taus: &[f32]) -> Vec<f32> {
        let mut cache = IqnCache::default();
        self.forward(obs, batch, taus, &mut cache);
        cache.z
    }

    /// Accumulate gradients from d loss / d Z (`batch x N`).
    pub fn backward(
        &self,
        grads: &mut [f32],
        obs: &[f32],
        batch: usize,
        cache: &mut IqnCache,
        dz: &[f32],
    ) {
        let p = &self.params.data;
        let f = self.feat;
        let n = cache.g.len() / f;
        let phi = cache.trunk.output();
        grads[self.head_b] += dz.iter().sum::<f32>();
        let (dphi, dg) = (&mut cache.dphi, &mut cache.dg);
        dphi.resize(batch * f, 0.0);
        gemm(batch, f, n, dz, false, &cache.g, false, dphi, false);
        dg.resize(n * f, 0.0);
        gemm(n, f, batch, dz, true, phi, false, dg, false);
        let w = &p[self.head_w..self.head_w + f];
        let gw = &mut grads[self.head_w..self.head_w + f];
        for (dg_row, e_row) in dg.chunks_exact_mut(f).zip(cache.emb.chunks_exact(f)) {
            for k in 0..f {
                gw[k] += dg_row[k] * e_row[k];
                // d pre-ReLU embedding
                dg_row[k] = if e_row[k] > 0.0 {
                    dg_row[k] * w[k]
                } else {
                    0.0
                };
            }
        }
        self.embed.backward_params(grads, &cache.cos, n, dg);
        let input = std::mem::take(&mut cache.trunk.input);
        let x = if self.input.is_identity() {
            obs
        } else {
            &input
        };
        self.trunk
            .backward(p, grads, x, batch, &mut cache.trunk, dphi, false);
        cache.trunk.input = input;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    /// Checks d(sum_i c_i y_i)/dparam against central differences (f64 sums).
    fn check_grads(
        params: &mut ParamSet,
        loss: &dyn Fn(&ParamSet) -> f64,
        analytic: &[f32],
        probes: usize,
    ) {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        for _ in 0..probes {
            let i = rng.gen_range(0..params.len());
            let old = params.data[i];
            let h = 1e-2f32;
            params.data[i] = old + h;
            let up = loss(params);
            params.data[i] = old - h;
            let down = loss(params);
            params.data[i] = old;
            let numeric = (up - down) / (2.0 * h as f64);
            let a = analytic[i] as f64;
            assert!(
                (numeric - a).abs() <= 2e-2 * a.abs().max(numeric.abs()) + 2e-3,
                "param {i}: analytic {a}, numeric {numeric}"
            );
        }
    }

    fn data(n: usize, seed: u64) -> Vec<f32> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        (0..n).map(|_| rng.gen_range(-1.0..1.0)).collect()
    }

    #[test]
    fn actor_backward_matches_finite_differences() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let (b, o, a) = (5, 4, 3);
        let mut actor = GaussianActor::new(o, a, &[6, 5], 1.0, &mut rng);
        let obs = data(b * o, 2);
        let c = data(b * a, 3);
        let mut cache = MlpCache::default();
        actor.forward(&obs, b, &mut cache);
        let mut g = vec![0.0; actor.params.len()];
        actor.backward(&mut g, &obs, b, &mut cache, &mut c.clone());
        let mut ps = actor.params.clone();
        let loss = |ps: &ParamSet| {
            let mut act = actor.clone();
            act.params = ps.clone();
            let m = act.mean(&obs, b);
            m.iter()
                .zip(&c)
                .map(|(m, c)| (*m as f64) * (*c as f64))
                .sum()
        };
        check_grads(&mut ps, &loss, &g, 60);
        actor.params = ps;
    }

    #[test]
    fn actor_with_encoder_backward_matches_finite_differences() {
        // row [direct 3 | privileged 4]; z (2) = encoder(privileged) appended to the direct input
        let mut rng = ChaCha8Rng::seed_from_u64(21);
        let (b, a) = (5, 3);
        let sel = |r: Range<usize>| InputSel {
            ranges: vec![r],
            row_width: 7,
        };
        let mut actor = GaussianActor::with_inputs(sel(0..3), 2, a, &[6, 5], 1.0, &mut rng);
        actor.add_encoder(sel(3..7), &[4], &mut rng);
        let obs = data(b * 7, 22);
        let c = data(b * a, 23);
        let mut cache = MlpCache::default();
        actor.forward(&obs, b, &mut cache);
        let mut g = vec![0.0; actor.params.len()];
        actor.backward(&mut g, &obs, b, &mut cache, &mut c.clone());
        let enc_params = actor
            .params
            .entries
            .iter()
            .filter(|e| e.name.starts_with("enc."))
            .map(|e| e.offset..e.offset + e.len())
            .collect::<Vec<_>>();
        assert!(!enc_params.is_empty());
        assert!(
            enc_params
                .iter()
                .any(|r| g[r.clone()].iter().any(|&v| v != 0.0)),
            "the encoder must receive gradient"
        );
        let mut ps = actor.params.clone();
        let loss = |ps: &ParamSet| {
            let mut act = actor.clone();
            act.params = ps.clone();
            let m = act.mean(&obs, b);
            m.iter()
                .zip(&c)
                .map(|(m, c)| (*m as f64) * (*c as f64))
                .sum()
        };
        check_grads(&mut ps, &loss, &g, 120);
    }

    #[test]
    fn critics_reading_some_groups_match_finite_differences() {
        let mut rng = ChaCha8Rng::seed_from_u64(31);
        let (b, w) = (4, 9);
        let sel = InputSel {
            ranges: vec![5..9, 0..2],
            row_width: w,
        };
        let critic = ScalarCritic::with_input(sel.clone(), &[6, 4], &mut rng);
        let obs = data(b * w, 32);
        let c = data(b, 33);
        let mut cache = MlpCache::default();
        critic.forward(&obs, b, &mut cache);
        let mut g = vec![0.0; critic.params.len()];
        critic.backward(&mut g, &obs, b, &mut cache, &mut c.clone());
        let mut ps = critic.params.clone();
        let loss = |ps: &ParamSet| {
            let mut cr = critic.clone();
            cr.params = ps.clone();
            let v = cr.values(&obs, b);
            v.iter()
                .zip(&c)
                .map(|(m, c)| (*m as f64) * (*c as f64))
                .sum()
        };
        check_grads(&mut ps, &loss, &g, 60);
        // the columns it does not read do not change its output
        let mut other = obs.clone();
        for row in other.chunks_exact_mut(w) {
            row[2..5].iter_mut().for_each(|v| *v += 1.0);
        }
        assert_eq!(critic.values(&obs, b), critic.values(&other, b));
        let iqn = IqnCritic::with_input(sel, &[6, 4], 8, &mut rng);
        let taus = [0.1, 0.5, 0.9];
        assert_eq!(
            iqn.quantiles(&obs, b, &taus),
            iqn.quantiles(&other, b, &taus)
        );
    }

    #[test]
    fn iqn_backward_matches_finite_differences() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let (b, o) = (6, 3);
        let critic = IqnCritic::new(o, &[7, 5], 8, &mut rng);
        let obs = data(b * o, 5);
        let taus = [0.05, 0.3, 0.5, 0.77];
        let c = data(b * taus.len(), 6);
        let mut cache = IqnCache::default();
        let _ = critic.forward(&obs, b, &taus, &mut cache);
        let mut g = vec![0.0; critic.params.len()];
        critic.backward(&mut g, &obs, b, &mut cache, &c);
        let mut ps = critic.params.clone();
        let loss = |ps: &ParamSet| {
            let mut cr = critic.clone();
            cr.params = ps.clone();
            let z = cr.quantiles(&obs, b, &taus);
            z.iter()
                .zip(&c)
                .map(|(m, c)| (*m as f64) * (*c as f64))
                .sum()
        };
        check_grads(&mut ps, &loss, &g, 120);
    }

    #[test]
    fn scalar_backward_matches_finite_differences() {
        let mut rng = ChaCha8Rng::seed_from_u64(8);
        let (b, o) = (4, 3);
        let critic = ScalarCritic::new(o, &[6, 4], &mut rng);
        let obs = data(b * o, 9);
        let c = data(b, 10);
        let mut cache = MlpCache::default();
        critic.forward(&obs, b, &mut cache);
        let mut g = vec![0.0; critic.params.len()];
        critic.backward(&mut g, &obs, b, &mut cache, &mut c.clone());
        let mut ps = critic.params.clone();
        let loss = |ps: &ParamSet| {
            let mut cr = critic.clone();
            cr.params = ps.clone();
            let v = cr.values(&obs, b);
            v.iter()
                .zip(&c)
                .map(|(m, c)| (*m as f64) * (*c as f64))
                .sum()
        };
        check_grads(&mut ps, &loss, &g, 60);
    }
}
