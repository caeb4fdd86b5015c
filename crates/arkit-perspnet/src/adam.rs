//! Adam (Kingma and Ba, 2015) over candle variables, with its state in the open so a
//! checkpoint can carry it and a resumed run continues the same run.
//!
//! candle's own `AdamW` keeps its moment estimates private, so a run resumed from
//! saved weights restarted them at zero: the first steps after a resume then moved
//! the weights by the full learning rate in every direction (Adam's bias correction
//! of fresh moments), and the run diverged from the uninterrupted one. Here the first
//! and second moments and the step count are saved beside the weights
//! ([`Adam::save`], [`Adam::load`]) and a resumed run is step for step the same.
//!
//! The update is the textbook one, without weight decay (candle's `AdamW` with
//! `weight_decay = 0`, PyTorch's `Adam`): with `g` the gradient and `t` the step,
//! `m = b1 m + (1 - b1) g`, `v = b2 v + (1 - b2) g^2`,
//! `x -= lr (m / (1 - b1^t)) / (sqrt(v / (1 - b2^t)) + eps)`. It runs as one loop over
//! each variable's flat `f32` buffer instead of a dozen tensor operations, each of
//! which allocated a tensor the size of the variable.

use std::collections::HashMap;
use std::path::Path;

use candle_core::backprop::GradStore;
use candle_core::{DType, Device, Result, Tensor, Var};

/// One variable and its moment estimates.
struct Slot {
    name: String,
    var: Var,
    m: Vec<f32>,
    v: Vec<f32>,
}

/// Adam over named `f32` variables.
pub struct Adam {
    slots: Vec<Slot>,
    step: usize,
    /// Learning rate of the next step.
    pub learning_rate: f64,
    /// Decay of the first moment (0.9).
    pub beta1: f64,
    /// Decay of the second moment (0.999).
    pub beta2: f64,
    /// Added to the root of the second moment (1e-8).
    pub eps: f64,
}

impl Adam {
    /// Adam with PyTorch's defaults (betas 0.9 / 0.999, eps 1e-8) over `vars`, each
    /// with a name that is unique and stable across runs (its checkpoint key).
    pub fn new(vars: Vec<(String, Var)>, learning_rate: f64) -> Result<Self> {
        let mut slots = Vec::with_capacity(vars.len());
        for (name, var) in vars {
            if var.dtype() != DType::F32 {
                candle_core::bail!("Adam: variable {name} is {:?}, not f32", var.dtype());
            }
            let n = var.elem_count();
            slots.push(Slot {
                name,
                var,
                m: vec![0.0; n],
                v: vec![0.0; n],
            });
        }
        Ok(Self {
            slots,
            step: 0,
            learning_rate,
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
        })
    }

    /// Steps taken so far (the `t` of the bias correction).
    pub fn steps(&self) -> usize {
        self.step
    }

    /// Back-propagates `loss` and takes one step.
    pub fn backward_step(&mut self, loss: &Tensor) -> Result<()> {
        let grads = loss.backward()?;
        self.step(&grads)
    }

    /// One step with the gradients in `grads`; variables without a gradient keep their
    /// value and moments (as in candle's and PyTorch's Adam).
    pub fn step(&mut self, grads: &GradStore) -> Result<()> {
        self.step += 1;
        let t = self.step as i32;
        let (b1, b2) = (self.beta1 as f32, self.beta2 as f32);
        let c1 = (1.0 / (1.0 - self.beta1.powi(t))) as f32;
        let c2 = (1.0 / (1.0 - self.beta2.powi(t))) as f32;
        let (lr, eps) = (self.learning_rate as f32, self.eps as f32);
        for slot in &mut self.slots {
            let Some(g) = grads.get(slot.var.as_tensor()) else {
                continue;
            };
            let g = g.flatten_all()?.to_vec1::<f32>()?;
            let mut x = slot.var.as_tensor().flatten_all()?.to_vec1::<f32>()?;
            for (((x, m), v), g) in x.iter_mut().zip(&mut slot.m).zip(&mut slot.v).zip(&g) {
                *m = b1 * *m + (1.0 - b1) * g;
                *v = b2 * *v + (1.0 - b2) * g * g;
                *x -= lr * (*m * c1) / ((*v * c2).sqrt() + eps);
            }
            let shape = slot.var.shape().clone();
            let device = slot.var.device().clone();
            slot.var.set(&Tensor::from_vec(x, shape, &device)?)?;
        }
        Ok(())
    }

    /// Writes the moments and the step count to a safetensors file (keys `m.NAME`,
    /// `v.NAME` and `step`). Write to a temporary name and rename for atomicity.
    pub fn save(&self, path: &Path) -> Result<()> {
        let device = Device::Cpu;
        let mut map = HashMap::new();
        for s in &self.slots {
            let shape = s.var.shape().clone();
            map.insert(
                format!("m.{}", s.name),
                Tensor::from_slice(&s.m, shape.clone(), &device)?,
            );
            map.insert(
                format!("v.{}", s.name),
                Tensor::from_slice(&s.v, shape, &device)?,
            );
        }
        map.insert(
            "step".to_string(),
            Tensor::new(&[self.step as i64], &device)?,
        );
        candle_core::safetensors::save(&map, path)
    }

    /// Reads what [`Adam::save`] wrote. The file's header is checked first (every
    /// variable's moments there with its shape, a one-element step count, nothing
    /// else), before any data is read; an error names the first entry that differs.
    pub fn load(&mut self, path: &Path) -> Result<()> {
        let mut st =
            crate::weights::safetensors_file::open(path).map_err(candle_core::Error::Msg)?;
        let mut want: HashMap<String, Vec<usize>> = HashMap::new();
        want.insert("step".to_string(), vec![1]);
        for s in &self.slots {
            want.insert(format!("m.{}", s.name), s.var.dims().to_vec());
            want.insert(format!("v.{}", s.name), s.var.dims().to_vec());
        }
        let have: HashMap<&str, &[usize]> = st
            .entries()
            .iter()
            .map(|e| (e.name.as_str(), e.shape.as_slice()))
            .collect();
        let mut keys: Vec<&String> = want.keys().collect();
        keys.sort();
        for key in keys {
            match have.get(key.as_str()) {
                None if key == "step" => candle_core::bail!("no step count"),
                None => candle_core::bail!("no {key}"),
                Some(shape) if *shape != want[key].as_slice() => {
                    candle_core::bail!("{key} has shape {shape:?}, the variable {:?}", want[key])
                }
                Some(_) => {}
            }
        }
        if let Some(extra) = have.keys().find(|k| !want.contains_key(**k)) {
            candle_core::bail!("{extra}: no such variable in the network");
        }
        let read = |st: &mut crate::weights::safetensors_file::SafetensorsFile<_>, key: &str| {
            st.read(key).map_err(candle_core::Error::Msg)
        };
        let step = read(&mut st, "step")?
            .to_dtype(DType::I64)?
            .to_vec1::<i64>()?[0];
        if step < 0 {
            candle_core::bail!("no step count");
        }
        let mut restored = Vec::with_capacity(self.slots.len());
        for s in &self.slots {
            let mut moment = |key: String| -> Result<Vec<f32>> {
                read(&mut st, &key)?
                    .to_dtype(DType::F32)?
                    .flatten_all()?
                    .to_vec1::<f32>()
            };
            restored.push((
                moment(format!("m.{}", s.name))?,
                moment(format!("v.{}", s.name))?,
            ));
        }
        for (s, (m, v)) in self.slots.iter_mut().zip(restored) {
            s.m = m;
            s.v = v;
        }
        self.step = step as usize;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_nn::{AdamW, Optimizer, ParamsAdamW};

    fn quadratic(x: &Var, y: &Var) -> Result<Tensor> {
        // A bowl with different curvature per coordinate, so the moments differ.
        let target = Tensor::new(&[1.0f32, -2.0, 0.5], &Device::Cpu)?;
        let a = (x.as_tensor() - &target)?.sqr()?.sum_all()?;
        let b = (y.as_tensor().sqr()? * 3.0)?.sum_all()?;
        a + b
    }

    fn vars() -> (Var, Var) {
        (
            Var::new(&[0.3f32, 0.1, -0.7], &Device::Cpu).unwrap(),
            Var::new(&[[2.0f32, -1.0], [0.25, 4.0]], &Device::Cpu).unwrap(),
        )
    }

    /// Cross-check against candle's `AdamW` (no weight decay), an independent
    /// implementation of the same update, over 25 steps with a changing rate.
    #[test]
    fn matches_candles_adamw_without_decay() {
        let (x1, y1) = vars();
        let (x2, y2) = vars();
        let mut ours = Adam::new(
            vec![("x".into(), x1.clone()), ("y".into(), y1.clone())],
            0.1,
        )
        .unwrap();
        let mut theirs = AdamW::new(
            vec![x2.clone(), y2.clone()],
            ParamsAdamW {
                lr: 0.1,
                weight_decay: 0.0,
                ..ParamsAdamW::default()
            },
        )
        .unwrap();
        for k in 0..25 {
            let lr = 0.1 / (1.0 + k as f64);
            ours.learning_rate = lr;
            theirs.set_learning_rate(lr);
            ours.backward_step(&quadratic(&x1, &y1).unwrap()).unwrap();
            theirs.backward_step(&quadratic(&x2, &y2).unwrap()).unwrap();
        }
        for (a, b) in [(&x1, &x2), (&y1, &y2)] {
            let a = a
                .as_tensor()
                .flatten_all()
                .unwrap()
                .to_vec1::<f32>()
                .unwrap();
            let b = b
                .as_tensor()
                .flatten_all()
                .unwrap()
                .to_vec1::<f32>()
                .unwrap();
            for (p, q) in a.iter().zip(&b) {
                assert!((p - q).abs() < 1e-5, "{a:?} vs {b:?}");
            }
        }
        // And it descends (each coordinate moves at most sum(lr) = 0.38 here).
        let (x0, y0) = vars();
        let start = quadratic(&x0, &y0).unwrap().to_scalar::<f32>().unwrap();
        let end = quadratic(&x1, &y1).unwrap().to_scalar::<f32>().unwrap();
        assert!(end < 0.75 * start, "{start} -> {end}");
    }

    /// Saving after 5 steps and loading into a fresh optimiser over copies of the
    /// variables gives the same next 5 steps, bit for bit; a fresh optimiser without
    /// the state does not.
    #[test]
    fn saved_state_resumes_the_same_run() {
        let (x, y) = vars();
        let mut a =
            Adam::new(vec![("x".into(), x.clone()), ("y".into(), y.clone())], 0.05).unwrap();
        for _ in 0..5 {
            a.backward_step(&quadratic(&x, &y).unwrap()).unwrap();
        }
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("adam.safetensors");
        a.save(&path).unwrap();
        let copy = |v: &Var| Var::from_tensor(&v.as_tensor().copy().unwrap()).unwrap();
        let (x2, y2) = (copy(&x), copy(&y));
        let (x3, y3) = (copy(&x), copy(&y));
        let mut b = Adam::new(
            vec![("x".into(), x2.clone()), ("y".into(), y2.clone())],
            0.05,
        )
        .unwrap();
        b.load(&path).unwrap();
        assert_eq!(b.steps(), 5);
        let mut fresh = Adam::new(
            vec![("x".into(), x3.clone()), ("y".into(), y3.clone())],
            0.05,
        )
        .unwrap();
        for _ in 0..5 {
            a.backward_step(&quadratic(&x, &y).unwrap()).unwrap();
            b.backward_step(&quadratic(&x2, &y2).unwrap()).unwrap();
            fresh.backward_step(&quadratic(&x3, &y3).unwrap()).unwrap();
        }
        let flat = |v: &Var| {
            v.as_tensor()
                .flatten_all()
                .unwrap()
                .to_vec1::<f32>()
                .unwrap()
        };
        assert_eq!(flat(&x), flat(&x2));
        assert_eq!(flat(&y), flat(&y2));
        assert_ne!(flat(&x), flat(&x3));
        // A file for other variables is refused with the name of what is missing.
        let mut other = Adam::new(vec![("z".into(), copy(&x))], 0.05).unwrap();
        let e = other.load(&path).unwrap_err().to_string();
        assert!(e.contains("m.z"), "{e}");
    }
}
