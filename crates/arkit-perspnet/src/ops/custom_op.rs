//! The one generic wrapper that turns an [`F32Op`] (a name, a forward on contiguous f32
//! values, a backward giving each input's gradient) into candle's `CustomOp1`,
//! `CustomOp2` or `CustomOp3`: the storage handling, the result's wrapping and the
//! gradient plumbing, written once for every op of this folder.

use candle_core::{CpuStorage, Layout, Result, Shape, Tensor};

/// A custom op with `N` inputs on contiguous f32 CPU tensors.
pub(crate) trait F32Op<const N: usize>: Send + Sync + 'static {
    /// candle's name of the op.
    const NAME: &'static str;

    /// The output's values and shape from each input's values and layout.
    fn forward(&self, inputs: [(&[f32], &Layout); N]) -> Result<(Vec<f32>, Shape)>;

    /// Each input's gradient (`None` where there is none) from the inputs, the output
    /// `res` and the output's gradient `grad`.
    fn backward(
        &self,
        inputs: [&Tensor; N],
        res: &Tensor,
        grad: &Tensor,
    ) -> Result<[Option<Tensor>; N]>;
}

/// An [`F32Op`] as a candle custom op.
struct Op<T>(T);

/// Runs `op`'s forward on CPU storages, each checked contiguous f32.
fn cpu_forward<const N: usize, T: F32Op<N>>(
    op: &T,
    storages: [(&CpuStorage, &Layout); N],
) -> Result<(CpuStorage, Shape)> {
    let mut inputs: [(&[f32], &Layout); N] = storages.map(|(_, l)| (&[][..], l));
    for (k, (s, l)) in storages.into_iter().enumerate() {
        inputs[k].0 = contiguous_f32(s, l)?;
    }
    let (y, shape) = op.forward(inputs)?;
    Ok((CpuStorage::F32(y), shape))
}

impl<T: F32Op<1>> candle_core::CustomOp1 for Op<T> {
    fn name(&self) -> &'static str {
        T::NAME
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        cpu_forward(&self.0, [(s, l)])
    }

    fn bwd(&self, x: &Tensor, res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        let [g] = self.0.backward([x], res, grad)?;
        Ok(g)
    }
}

impl<T: F32Op<2>> candle_core::CustomOp2 for Op<T> {
    fn name(&self) -> &'static str {
        T::NAME
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        cpu_forward(&self.0, [(s1, l1), (s2, l2)])
    }

    fn bwd(
        &self,
        a: &Tensor,
        b: &Tensor,
        res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let [ga, gb] = self.0.backward([a, b], res, grad)?;
        Ok((ga, gb))
    }
}

impl<T: F32Op<3>> candle_core::CustomOp3 for Op<T> {
    fn name(&self) -> &'static str {
        T::NAME
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        cpu_forward(&self.0, [(s1, l1), (s2, l2), (s3, l3)])
    }

    fn bwd(
        &self,
        a: &Tensor,
        b: &Tensor,
        c: &Tensor,
        res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let [ga, gb, gc] = self.0.backward([a, b, c], res, grad)?;
        Ok((ga, gb, gc))
    }
}

/// Applying an [`F32Op`] to tensors (the first input is `self`).
pub(crate) trait ApplyF32Op {
    /// A one-input op.
    fn apply_f32_op1<T: F32Op<1>>(&self, op: T) -> Result<Tensor>;
    /// A two-input op.
    fn apply_f32_op2<T: F32Op<2>>(&self, b: &Tensor, op: T) -> Result<Tensor>;
    /// A three-input op.
    fn apply_f32_op3<T: F32Op<3>>(&self, b: &Tensor, c: &Tensor, op: T) -> Result<Tensor>;
}

impl ApplyF32Op for Tensor {
    fn apply_f32_op1<T: F32Op<1>>(&self, op: T) -> Result<Tensor> {
        self.apply_op1(Op(op))
    }

    fn apply_f32_op2<T: F32Op<2>>(&self, b: &Tensor, op: T) -> Result<Tensor> {
        self.apply_op2(b, Op(op))
    }

    fn apply_f32_op3<T: F32Op<3>>(&self, b: &Tensor, c: &Tensor, op: T) -> Result<Tensor> {
        self.apply_op3(b, c, Op(op))
    }
}

/// A tensor of the values `v` with the shape and device of `like`.
pub(crate) fn like(v: Vec<f32>, like: &Tensor) -> Result<Tensor> {
    Tensor::from_vec(v, like.shape(), like.device())
}

/// The contiguous f32 values of a CPU storage.
pub(crate) fn contiguous_f32<'a>(
    s: &'a candle_core::CpuStorage,
    l: &candle_core::Layout,
) -> Result<&'a [f32]> {
    let data = s.as_slice::<f32>()?;
    match l.contiguous_offsets() {
        Some((a, b)) => Ok(&data[a..b]),
        None => candle_core::bail!("expected a contiguous f32 tensor"),
    }
}

/// Runs `f` on the contiguous f32 values of a CPU tensor (copying only when the
/// tensor is not contiguous).
pub(crate) fn with_f32<R>(t: &Tensor, f: impl FnOnce(&[f32]) -> R) -> Result<R> {
    let t = t.contiguous()?;
    let (storage, layout) = t.storage_and_layout();
    match &*storage {
        candle_core::Storage::Cpu(cpu) => Ok(f(contiguous_f32(cpu, layout)?)),
        _ => candle_core::bail!("expected a CPU tensor"),
    }
}
