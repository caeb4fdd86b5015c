//! The reference PerspNet (`arkit_perspnet`): layers against hand values and
//! candle's own ops, the `paper` shapes and parameter counts, and `tiny` training.

mod layers {
    //! Hand-checked tests of the custom differentiable layers.

    use arkit_perspnet::layers::*;
    use candle_core::{Device, Result, Tensor, Var};

    fn close(a: &[f32], b: &[f32], tol: f32) {
        assert_eq!(a.len(), b.len());
        for (i, (x, y)) in a.iter().zip(b).enumerate() {
            assert!((x - y).abs() <= tol, "index {i}: {x} vs {y}");
        }
    }

    #[test]
    fn upsample_matches_hand_values_and_candle() -> Result<()> {
        let dev = Device::Cpu;
        // 1 x 1 x 2 x 2 -> 4 x 4 with align_corners=True: source positions 0, 1/3, 2/3, 1.
        let x = Tensor::new(&[[[[0f32, 3.], [6., 9.]]]], &dev)?;
        let y = upsample2x_bilinear(&x)?;
        let got: Vec<f32> = y.flatten_all()?.to_vec1()?;
        let want = [
            0., 1., 2., 3., 2., 3., 4., 5., 4., 5., 6., 7., 6., 7., 8., 9.,
        ];
        close(&got, &want, 1e-5);
        // 1-D matrix for 3 -> 6: positions i * 2/5.
        let m = interp_matrix_align_corners(3, 6);
        close(&m[3..6], &[0.6, 0.4, 0.0], 1e-6);
        close(&m[6..9], &[0.2, 0.8, 0.0], 1e-6);
        close(&m[15..18], &[0.0, 0.0, 1.0], 1e-6);
        // Against candle's (non-differentiable) kernel on a random tensor.
        let x = Tensor::randn(0f32, 1., (2, 3, 5, 7), &dev)?;
        let a: Vec<f32> = upsample2x_bilinear(&x)?.flatten_all()?.to_vec1()?;
        let b: Vec<f32> = x
            .upsample_bilinear2d(10, 14, true)?
            .flatten_all()?
            .to_vec1()?;
        close(&a, &b, 1e-5);
        // Gradient: sum of outputs -> each input's grad is the column sums of the matrices.
        let v = Var::from_tensor(&Tensor::ones((1, 1, 2, 2), candle_core::DType::F32, &dev)?)?;
        let g = upsample2x_bilinear(v.as_tensor())?.sum_all()?.backward()?;
        let gv: Vec<f32> = g.get(v.as_tensor()).unwrap().flatten_all()?.to_vec1()?;
        close(&gv, &[4., 4., 4., 4.], 1e-5);
        Ok(())
    }

    #[test]
    fn point_sampler_matches_grid_sample() -> Result<()> {
        let dev = Device::Cpu;
        // 4 x 4 map with value = 10 * y + x, two channels (second = -first).
        let vals: Vec<f32> = (0..16).map(|i| (10 * (i / 4) + i % 4) as f32).collect();
        let neg: Vec<f32> = vals.iter().map(|v| -v).collect();
        let map = Tensor::from_vec([vals, neg].concat(), (1, 2, 4, 4), &dev)?;
        // u = 0.5, v = 0.5 -> pixel (1.5, 1.5) -> 16.5.
        // u = 0.375, v = 0.125 -> pixel (1.0, 0.0) -> 1.
        // u = 0.0, v = 0.5 -> pixel (-0.5, 1.5): half weight on x=0 column (zeros padding) -> 0.5 * 15 = 7.5.
        // u = 1.0, v = 1.0 -> pixel (3.5, 3.5): only (3,3) with weight 0.25 -> 8.25.
        let uv = Tensor::new(
            &[[0.5f32, 0.5], [0.375, 0.125], [0.0, 0.5], [1.0, 1.0]],
            &dev,
        )?;
        let s = PointSampler::new(&uv, 4, 4)?;
        let out = s.sample(&map)?; // 1 x 2 x 4
        assert_eq!(out.dims(), &[1, 2, 4]);
        let got: Vec<f32> = out.flatten_all()?.to_vec1()?;
        close(
            &got,
            &[16.5, 1.0, 7.5, 8.25, -16.5, -1.0, -7.5, -8.25],
            1e-5,
        );
        Ok(())
    }

    #[test]
    fn gather_pixels_picks_per_batch() -> Result<()> {
        let dev = Device::Cpu;
        let x = Tensor::arange(0f32, 2. * 3. * 4., &dev)?.reshape((2, 3, 2, 2))?;
        let choose = Tensor::new(&[[0u32, 3], [1, 1]], &dev)?;
        let g = gather_pixels(&x, &choose)?; // 2 x 2 x 3
        let got: Vec<f32> = g.flatten_all()?.to_vec1()?;
        // batch 0, pixel 0: channels 0,4,8; pixel 3: 3,7,11; batch 1 pixel 1: 13,17,21.
        close(
            &got,
            &[0., 4., 8., 3., 7., 11., 13., 17., 21., 13., 17., 21.],
            0.0,
        );
        Ok(())
    }

    #[test]
    fn positional_encoding_formula() {
        let pe = positional_encoding_at(64, 3.0, 5.0);
        let div1 = (-(2.0f64) * 10000f64.ln() / 32.0).exp();
        close(
            &pe[..4],
            &[
                3f32.sin(),
                3f32.cos(),
                (3.0 * div1).sin() as f32,
                (3.0 * div1).cos() as f32,
            ],
            1e-6,
        );
        close(&pe[32..34], &[5f32.sin(), 5f32.cos()], 1e-6);
        // The map layout matches the point evaluation.
        let map = positional_encoding_map(8, 3, 4);
        let p = positional_encoding_at(8, 2.0, 1.0);
        for (c, v) in p.iter().enumerate() {
            assert_eq!(map[(c * 3 + 1) * 4 + 2], *v);
        }
    }

    #[test]
    fn point_reads_match_the_candle_compositions_forward_and_backward() -> Result<()> {
        // The f64 path is candle's composition (index_select, weighted sum); the f32
        // path is the CPU op.
        let dev = Device::Cpu;
        let f64_path = |f: &dyn Fn(&Tensor) -> Result<Tensor>, t: &Tensor| -> Result<Tensor> {
            f(&t.to_dtype(candle_core::DType::F64)?)?.to_dtype(candle_core::DType::F32)
        };
        let uv = Tensor::new(
            &[
                [0.1f32, 0.2],
                [0.0, 1.0],
                [0.5, 0.5],
                [0.97, 0.33],
                [0.26, 0.74],
            ],
            &dev,
        )?;
        let sampler = PointSampler::new(&uv, 5, 7)?;
        let map = Var::from_tensor(&Tensor::randn(0f32, 1., (2, 3, 5, 7), &dev)?)?;
        same_forward_and_gradients(
            |t| sampler.sample(&t[0]),
            |t| f64_path(&|x| sampler.sample(x), &t[0]),
            std::slice::from_ref(&map),
            1e-5,
        )?;
        // Repeated pixels accumulate their gradients.
        let choose = Tensor::new(&[[3u32, 0, 34, 3], [7, 7, 12, 1]], &dev)?;
        same_forward_and_gradients(
            |t| gather_pixels(&t[0], &choose),
            |t| f64_path(&|x| gather_pixels(x, &choose), &t[0]),
            std::slice::from_ref(&map),
            1e-5,
        )?;
        assert!(gather_pixels(map.as_tensor(), &Tensor::new(&[[35u32], [0]], &dev)?).is_err());
        Ok(())
    }

    #[test]
    fn max_pool_op_matches_the_view_composition_forward_and_backward() -> Result<()> {
        // Distinct values (no ties), so both send each gradient to the same input;
        // non-negative, where the views' zero padding equals PyTorch's.
        for (h, w) in [(8, 8), (7, 9), (5, 4)] {
            let x = Var::from_tensor(&Tensor::rand(0f32, 1., (2, 3, h, w), &Device::Cpu)?)?;
            same_forward_and_gradients(
                |t| max_pool_3x3_s2_p1(&t[0]),
                |t| max_pool_3x3_s2_p1_views(&t[0]),
                std::slice::from_ref(&x),
                1e-6,
            )?;
        }
        // Negative inputs: padding never wins (PyTorch's -inf padding).
        let x = Tensor::new(&[-3f32, -1.0, -2.0, -4.0], &Device::Cpu)?.reshape((1, 1, 2, 2))?;
        close(
            &max_pool_3x3_s2_p1(&x)?.flatten_all()?.to_vec1()?,
            &[-1.0],
            0.0,
        );
        Ok(())
    }

    #[test]
    fn max_pool_matches_reference() -> Result<()> {
        let dev = Device::Cpu;
        for (h, w) in [(8, 8), (7, 9), (96, 96)] {
            let x = Tensor::rand(0f32, 1., (2, 3, h, w), &dev)?;
            let got = max_pool_3x3_s2_p1(&x)?;
            // Reference: brute force.
            let xv: Vec<f32> = x.flatten_all()?.to_vec1()?;
            let (oh, ow) = ((h - 1) / 2 + 1, (w - 1) / 2 + 1);
            assert_eq!(got.dims(), &[2, 3, oh, ow]);
            let gv: Vec<f32> = got.flatten_all()?.to_vec1()?;
            for bc in 0..6 {
                for i in 0..oh {
                    for j in 0..ow {
                        let mut m = f32::MIN;
                        for di in 0..3 {
                            for dj in 0..3 {
                                let (y, x) = (2 * i + di, 2 * j + dj);
                                if y >= 1 && x >= 1 && y - 1 < h && x - 1 < w {
                                    m = m.max(xv[bc * h * w + (y - 1) * w + (x - 1)]);
                                }
                            }
                        }
                        assert_eq!(gv[(bc * oh + i) * ow + j], m);
                    }
                }
            }
        }
        Ok(())
    }

    #[test]
    fn dropout2d_drops_whole_channels() -> Result<()> {
        let dev = Device::Cpu;
        let x = Tensor::ones((4, 64, 3, 3), candle_core::DType::F32, &dev)?;
        let mut rng = arkit_core::Rng::new(1);
        let y = dropout2d(&x, 0.5, Some(&mut rng))?;
        let v: Vec<f32> = y.flatten_all()?.to_vec1()?;
        for ch in v.chunks(9) {
            assert!(ch.iter().all(|&a| a == ch[0]) && (ch[0] == 0.0 || (ch[0] - 2.0).abs() < 1e-6));
        }
        // About half of the 256 channels dropped, and the same seed drops the same.
        let dropped = v.chunks(9).filter(|ch| ch[0] == 0.0).count();
        assert!((96..160).contains(&dropped), "{dropped}");
        let again: Vec<f32> = dropout2d(&x, 0.5, Some(&mut arkit_core::Rng::new(1)))?
            .flatten_all()?
            .to_vec1()?;
        assert_eq!(v, again);
        let same: Vec<f32> = dropout2d(&x, 0.5, None)?.flatten_all()?.to_vec1()?;
        assert!(same.iter().all(|&a| a == 1.0));
        Ok(())
    }

    #[test]
    fn imagenet_normalisation() -> Result<()> {
        let dev = Device::Cpu;
        let x = Tensor::full(0.5f32, (1, 3, 1, 1), &dev)?;
        let y: Vec<f32> = imagenet_normalize(&x)?.flatten_all()?.to_vec1()?;
        close(
            &y,
            &[
                (0.5 - 0.485) / 0.229,
                (0.5 - 0.456) / 0.224,
                (0.5 - 0.406) / 0.225,
            ],
            1e-6,
        );
        Ok(())
    }

    #[test]
    fn im2col_conv_matches_candle_conv() -> Result<()> {
        let dev = Device::Cpu;
        for (k, stride, pad, h, w) in [
            (3, 1, 1, 9, 7),
            (3, 2, 1, 12, 12),
            (7, 2, 3, 16, 16),
            (1, 2, 0, 8, 8),
            (1, 1, 0, 5, 6),
            (3, 2, 1, 7, 9),
        ] {
            let x = Tensor::randn(0f32, 1., (2, 4, h, w), &dev)?;
            let wt = Tensor::randn(0f32, 1., (5, 4, k, k), &dev)?;
            let a = conv2d_im2col(&x, &wt, stride, pad)?;
            let b = x.conv2d(&wt, pad, stride, 1, 1)?;
            assert_eq!(a.dims(), b.dims());
            let d: f32 = (a - b)?.abs()?.max_all()?.to_scalar()?;
            assert!(d < 1e-4, "k{k} s{stride} p{pad}: {d}");
        }
        Ok(())
    }

    #[test]
    fn fast_conv_gradients_match_builtin() -> Result<()> {
        let dev = Device::Cpu;
        for (k, stride, pad, h, w) in [
            (3, 1, 1, 9, 7),
            (3, 2, 1, 12, 12),
            (7, 2, 3, 16, 16),
            (1, 2, 0, 8, 8),
            (1, 1, 0, 5, 6),
            (3, 2, 1, 7, 9),
        ] {
            let x = Var::from_tensor(&Tensor::randn(0f32, 1., (2, 4, h, w), &dev)?)?;
            let wt = Var::from_tensor(&Tensor::randn(0f32, 1., (5, 4, k, k), &dev)?)?;
            let a = conv2d_fast(x.as_tensor(), wt.as_tensor(), stride, pad)?;
            let b = x.as_tensor().conv2d(wt.as_tensor(), pad, stride, 1, 1)?;
            let d: f32 = (&a - &b)?.abs()?.max_all()?.to_scalar()?;
            assert!(d < 1e-4, "fwd k{k} s{stride}: {d}");
            let r = Tensor::randn(0f32, 1., a.shape(), &dev)?;
            let ga = (&a * &r)?.sum_all()?.backward()?;
            let gb = (&b * &r)?.sum_all()?.backward()?;
            for v in [&x, &wt] {
                let d: f32 = (ga.get(v.as_tensor()).unwrap() - gb.get(v.as_tensor()).unwrap())?
                    .abs()?
                    .max_all()?
                    .to_scalar()?;
                assert!(d < 1e-3, "grad k{k} s{stride} p{pad} {h}x{w}: {d}");
            }
        }
        Ok(())
    }

    #[test]
    fn fused_batch_norm_matches_candle() -> Result<()> {
        use candle_core::ModuleT;
        use candle_nn::{VarBuilder, VarMap};
        let dev = Device::Cpu;
        let acts = [Act::None, Act::Relu, Act::Leaky(0.1)];
        for (train, act) in [true, false].into_iter().flat_map(|t| acts.map(|a| (t, a))) {
            let vm1 = VarMap::new();
            let vm2 = VarMap::new();
            let a = BatchNorm2d::new(
                VarBuilder::from_varmap(&vm1, candle_core::DType::F32, &dev),
                5,
                0.3,
                1e-5,
                0.1,
            )?;
            let b = batch_norm(
                VarBuilder::from_varmap(&vm2, candle_core::DType::F32, &dev),
                5,
                0.3,
                1e-5,
                0.1,
            )?;
            // Same parameters in both.
            for (k, v) in vm2.data().lock().unwrap().iter() {
                vm1.data().lock().unwrap()[k].set(v.as_tensor())?;
            }
            let x = Var::from_tensor(&Tensor::randn(0.5f32, 2., (3, 5, 4, 6), &dev)?)?;
            let r = Tensor::randn(0f32, 1., (3, 5, 4, 6), &dev)?;
            // Ours fused with the activation; candle's followed by candle's ops.
            let ya = a.forward_act(x.as_tensor(), train, act)?;
            let yb = b.forward_t(x.as_tensor(), train)?;
            let yb = match act {
                Act::None => yb,
                Act::Relu => yb.relu()?,
                Act::Leaky(s) => (yb.relu()?.affine(1.0 - s, 0.0)? + yb.affine(s, 0.0)?)?,
            };
            let d: f32 = (&ya - &yb)?.abs()?.max_all()?.to_scalar()?;
            assert!(d < 1e-4, "fwd train={train} {act:?}: {d}");
            let ga = (&ya * &r)?.sum_all()?.backward()?;
            let gb = (&yb * &r)?.sum_all()?.backward()?;
            let d: f32 = (ga.get(x.as_tensor()).unwrap() - gb.get(x.as_tensor()).unwrap())?
                .abs()?
                .max_all()?
                .to_scalar()?;
            assert!(d < 1e-3, "dx train={train} {act:?}: {d}");
            for name in ["weight", "bias"] {
                let ta = vm1.data().lock().unwrap()[name].as_tensor().clone();
                let tb = vm2.data().lock().unwrap()[name].as_tensor().clone();
                let d: f32 = (ga.get(&ta).unwrap() - gb.get(&tb).unwrap())?
                    .abs()?
                    .max_all()?
                    .to_scalar()?;
                assert!(d < 1e-3, "d{name} train={train} {act:?}: {d}");
            }
            for name in ["running_mean", "running_var"] {
                let ta = vm1.data().lock().unwrap()[name].as_tensor().clone();
                let tb = vm2.data().lock().unwrap()[name].as_tensor().clone();
                let d: f32 = (ta - tb)?.abs()?.max_all()?.to_scalar()?;
                assert!(d < 1e-4, "{name} train={train}: {d}");
            }
        }
        Ok(())
    }

    #[test]
    fn two_tap_resize_equals_the_interpolation_matmuls_forward_and_backward() -> Result<()> {
        let dev = Device::Cpu;
        for (h, w, oh, ow) in [
            (3, 4, 6, 8),
            (6, 6, 12, 12),
            (5, 3, 7, 4),
            (1, 4, 2, 8),
            (4, 5, 2, 3),
        ] {
            let x = Var::from_tensor(&Tensor::randn(0f32, 1., (2, 3, h, w), &dev)?)?;
            let a = upsample_bilinear_align_corners(x.as_tensor(), oh, ow)?;
            assert_eq!(a.dims(), &[2, 3, oh, ow], "{h}x{w} -> {oh}x{ow}");
            same_forward_and_gradients(
                |t| upsample_bilinear_align_corners(&t[0], oh, ow),
                |t| upsample_bilinear_matmul(&t[0], oh, ow),
                std::slice::from_ref(&x),
                1e-5,
            )?;
        }
        Ok(())
    }

    #[test]
    fn fused_log_softmax_matches_candle_forward_and_backward() -> Result<()> {
        let dev = Device::Cpu;
        // Rows with large offsets check the max shift.
        let x = (Tensor::randn(0f32, 3., (2, 5, 17), &dev)?
            + Tensor::new(&[0f32, 80.0], &dev)?
                .reshape((2, 1, 1))?
                .broadcast_as((2, 5, 17))?)?;
        let x = Var::from_tensor(&x)?;
        // Rows of the softmax sum to 1.
        let sums: Vec<f32> = log_softmax_last(x.as_tensor())?
            .exp()?
            .sum(2)?
            .flatten_all()?
            .to_vec1()?;
        close(&sums, &[1.0; 10], 1e-5);
        same_forward_and_gradients_within(
            |t| log_softmax_last(&t[0]),
            |t| candle_nn::ops::log_softmax(&t[0], candle_core::D::Minus1),
            std::slice::from_ref(&x),
            1e-5,
            Some(1e-4),
        )
    }

    #[test]
    fn point_linear_matches_candle_linear_forward_and_backward() -> Result<()> {
        use candle_core::Module;
        use candle_nn::{VarBuilder, VarMap};
        let dev = Device::Cpu;
        let vm = VarMap::new();
        let layer = PointLinear::new(
            VarBuilder::from_varmap(&vm, candle_core::DType::F32, &dev),
            6,
            5,
            0.5,
        )?;
        // A non-zero bias, so that its gradient and broadcast are tested.
        for (k, v) in vm.data().lock().unwrap().iter() {
            if k == "bias" {
                v.set(&Tensor::new(&[0.5f32, -1.0, 2.0, 0.0, 0.25], &dev)?)?;
            }
        }
        let reference = candle_nn::Linear::new(layer.weight().clone(), Some(layer.bias().clone()));
        for dims in [vec![7, 6], vec![3, 4, 6]] {
            let x = Var::from_tensor(&Tensor::randn(0f32, 1., dims.as_slice(), &dev)?)?;
            let a = layer.forward(x.as_tensor())?;
            let b = reference.forward(x.as_tensor())?;
            assert_eq!(a.dims(), b.dims());
            let d: f32 = (&a - &b)?.abs()?.max_all()?.to_scalar()?;
            assert!(d < 1e-5, "forward {dims:?}: {d}");
            let r = Tensor::randn(0f32, 1., a.shape(), &dev)?;
            let ga = (&a * &r)?.sum_all()?.backward()?;
            let gb = (&b * &r)?.sum_all()?.backward()?;
            for t in [x.as_tensor(), layer.weight(), layer.bias()] {
                let d: f32 = (ga.get(t).unwrap() - gb.get(t).unwrap())?
                    .abs()?
                    .max_all()?
                    .to_scalar()?;
                assert!(d < 1e-4, "gradient {dims:?} {:?}: {d}", t.dims());
            }
        }
        Ok(())
    }

    /// `f` and `g` agree forward (within `tol`) and in the gradient of every input
    /// (within `grad_tol`, or `tol` when `None`).
    fn same_forward_and_gradients_within(
        f: impl Fn(&[Tensor]) -> Result<Tensor>,
        g: impl Fn(&[Tensor]) -> Result<Tensor>,
        inputs: &[Var],
        tol: f32,
        grad_tol: Option<f32>,
    ) -> Result<()> {
        let ts: Vec<Tensor> = inputs.iter().map(|v| v.as_tensor().clone()).collect();
        let (a, b) = (f(&ts)?, g(&ts)?);
        assert_eq!(a.dims(), b.dims());
        let d: f32 = (&a - &b)?.abs()?.flatten_all()?.max(0)?.to_scalar()?;
        assert!(d < tol, "forward: {d}");
        let r = Tensor::randn(0f32, 1., a.shape(), &Device::Cpu)?;
        let ga = (&a * &r)?.sum_all()?.backward()?;
        let gb = (&b * &r)?.sum_all()?.backward()?;
        for (i, t) in ts.iter().enumerate() {
            let d: f32 = (ga.get(t).unwrap() - gb.get(t).unwrap())?
                .abs()?
                .flatten_all()?
                .max(0)?
                .to_scalar()?;
            assert!(d < grad_tol.unwrap_or(tol), "gradient of input {i}: {d}");
        }
        Ok(())
    }

    /// [`same_forward_and_gradients_within`] with one tolerance.
    fn same_forward_and_gradients(
        f: impl Fn(&[Tensor]) -> Result<Tensor>,
        g: impl Fn(&[Tensor]) -> Result<Tensor>,
        inputs: &[Var],
        tol: f32,
    ) -> Result<()> {
        same_forward_and_gradients_within(f, g, inputs, tol, None)
    }

    #[test]
    fn row_ops_match_candle_forward_and_backward() -> Result<()> {
        let dev = Device::Cpu;
        let h = Var::from_tensor(&Tensor::randn(0f32, 1., (3, 5, 4), &dev)?)?;
        let r = Var::from_tensor(&Tensor::randn(0f32, 1., (3, 1, 4), &dev)?)?;
        same_forward_and_gradients(
            |t| add_rows_relu(&t[0], &t[1]),
            |t| t[0].broadcast_add(&t[1])?.relu(),
            &[h.clone(), r],
            1e-5,
        )?;
        same_forward_and_gradients(
            |t| mean_points(&t[0]),
            |t| t[0].mean_keepdim(1),
            std::slice::from_ref(&h),
            1e-5,
        )?;
        let logits = Tensor::randn(0f32, 2., (3, 5, 9), &dev)?;
        let log_p = Var::from_tensor(&candle_nn::ops::log_softmax(&logits, 2)?)?;
        same_forward_and_gradients(
            |t| row_entropy(&t[0]),
            |t| (t[0].exp()? * &t[0])?.sum(2)?.neg(),
            &[log_p],
            1e-5,
        )?;
        // Hand value: the uniform distribution over 4 has entropy ln 4.
        let uniform = Tensor::new(&[[0.25f32; 4]], &dev)?.log()?;
        close(&row_entropy(&uniform)?.to_vec1()?, &[4f32.ln()], 1e-6);
        // point_linear without a bias is the plain product.
        let x = Var::from_tensor(&Tensor::randn(0f32, 1., (2, 3, 4), &dev)?)?;
        let w = Var::from_tensor(&Tensor::randn(0f32, 1., (5, 4), &dev)?)?;
        same_forward_and_gradients(
            |t| point_linear(&t[0], &t[1], None),
            |t| t[0].broadcast_matmul(&t[1].t()?),
            &[x, w],
            1e-4,
        )
    }

    #[test]
    fn fused_activations_match_hand_values_and_gradients() -> Result<()> {
        let dev = Device::Cpu;
        let x = Var::new(&[-2f32, -0.5, 0.0, 3.0], &dev)?;
        let w = Tensor::new(&[1f32, 2.0, 3.0, 4.0], &dev)?;
        let y = leaky_relu(x.as_tensor(), 0.1)?;
        close(&y.to_vec1()?, &[-0.2, -0.05, 0.0, 3.0], 1e-6);
        // d/dx sum(w * act(x)): w * slope, PyTorch's convention at 0 (the slope).
        let g = (&y * &w)?.sum_all()?.backward()?;
        close(
            &g.get(x.as_tensor()).unwrap().to_vec1()?,
            &[0.1, 0.2, 0.3, 4.0],
            1e-6,
        );
        let y = relu(x.as_tensor())?;
        close(&y.to_vec1()?, &[0.0, 0.0, 0.0, 3.0], 0.0);
        let g = (&y * &w)?.sum_all()?.backward()?;
        close(
            &g.get(x.as_tensor()).unwrap().to_vec1()?,
            &[0.0, 0.0, 0.0, 4.0],
            0.0,
        );
        // relu(a + b): both inputs get the gradient where the sum is positive.
        let b = Var::new(&[1f32, 1.0, -1.0, -4.0], &dev)?;
        let y = add_relu(x.as_tensor(), b.as_tensor())?;
        close(&y.to_vec1()?, &[0.0, 0.5, 0.0, 0.0], 0.0);
        let g = (&y * &w)?.sum_all()?.backward()?;
        for v in [&x, &b] {
            close(
                &g.get(v.as_tensor()).unwrap().to_vec1()?,
                &[0.0, 2.0, 0.0, 0.0],
                0.0,
            );
        }
        Ok(())
    }
}

mod shapes {
    //! One forward pass of the `paper` configuration: checks every intermediate
    //! shape and reports the parameter count against the official numbers.

    use arkit_perspnet::{PerspNet, PerspNetConfig};
    use arkit_perspnet::{parameter_count, synthetic_vertex_uv};
    use candle_core::{DType, Device, Result, Tensor};
    use candle_nn::{VarBuilder, VarMap};

    #[test]
    fn paper_forward_shapes_and_parameter_count() -> Result<()> {
        let dev = Device::Cpu;
        let cfg = PerspNetConfig::paper();
        let varmap = VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, &dev);
        let uv = synthetic_vertex_uv(cfg.vertices, &dev)?;
        let net = PerspNet::new(&cfg, &uv, vb)?;

        let total = parameter_count(&varmap, "");
        let dense = parameter_count(&varmap, "cnn.");
        println!(
            "parameters: full {:.3} M (official 16.97 M), encoder+decoders {:.3} M (official 15.12 M), head {:.3} M",
            total as f64 / 1e6,
            dense as f64 / 1e6,
            (total - dense) as f64 / 1e6
        );
        assert!((total as f64 / 1e6 - 16.97).abs() < 0.01, "total {total}");
        assert!((dense as f64 / 1e6 - 15.12).abs() < 0.01, "dense {dense}");

        let (b, s, m) = (1usize, 192usize, 1024usize);
        let img = Tensor::randn(0f32, 1., (b, 3, s, s), &dev)?;
        let choose: Vec<u32> = (0..m as u32).map(|i| (i * 37) % (s * s) as u32).collect();
        let choose = Tensor::from_vec(choose, (b, m), &dev)?;
        let t0 = std::time::Instant::now();
        let out = net.forward(&img, &choose, false)?;
        println!("paper forward (eval, batch 1): {:?}", t0.elapsed());

        let e = &out.dense.encoder;
        assert_eq!(e.x2s.dims(), &[b, 64, 96, 96]);
        assert_eq!(e.x4s.dims(), &[b, 64, 48, 48]);
        assert_eq!(e.x8s.dims(), &[b, 128, 24, 24]);
        assert_eq!(e.x16s.dims(), &[b, 256, 12, 12]);
        assert_eq!(e.x32s.dims(), &[b, 512, 6, 6]);
        assert_eq!(e.fc.dims(), &[b, 256, 6, 6]);
        let want = [
            [b, 256, 12, 12],
            [b, 128, 24, 24],
            [b, 64, 48, 48],
            [b, 32, 96, 96],
        ];
        for (t, w) in out.dense.decoder_2d.iter().zip(&want) {
            assert_eq!(t.dims(), w);
        }
        for (t, w) in out.dense.decoder_uv.iter().zip(&want) {
            assert_eq!(t.dims(), w);
        }
        assert_eq!(out.dense.image_features.dims(), &[b, 32, s, s]);
        assert_eq!(out.dense.seg_logits.dims(), &[b, 2, s, s]);
        assert_eq!(out.dense.uv_features.dims(), &[b, 32, s, s]);
        assert_eq!(out.dense.uv_map.dims(), &[b, 3, s, s]);
        assert_eq!(out.assign_logits.dims(), &[b, m, 1220]);
        assert_eq!(out.vertices.dims(), &[b, 1220, 3]);
        let a = out.assignment()?;
        assert_eq!(a.dims(), &[b, m, 1220]);
        let row_sum: f32 = a.sum(2)?.mean_all()?.to_scalar()?;
        assert!((row_sum - 1.0).abs() < 1e-4);
        assert_eq!(out.correspondences()?.dims(), &[b, m, 3]);
        let uv_max: f32 = out.dense.uv_map.abs()?.max_all()?.to_scalar()?;
        assert!(uv_max <= 1.0);
        Ok(())
    }
}

mod train {
    //! `tiny` configuration: loss terms behave, a few AdamW steps on one fixed
    //! batch reduce the total loss, and weights survive a safetensors round trip.

    use arkit_perspnet::{
        CorrTarget, LossTargets, LossVariant, PerspNet, PerspNetConfig, PerspNetLoss,
    };
    use arkit_perspnet::{
        LossWeights, kl_loss, perspnet_loss, seg_cross_entropy, smooth_l1_sum_mean,
    };
    use arkit_perspnet::{synthetic_vertex_uv, trainable_vars};
    use candle_core::{DType, Device, Result, Tensor};
    use candle_nn::{AdamW, Optimizer, ParamsAdamW, VarBuilder, VarMap};

    struct Batch {
        img: Tensor,
        choose: Tensor,
        nocs: Tensor,
        model: Tensor,
        mask: Tensor,
        ids: Tensor,
        weights: Tensor,
    }

    fn batch(cfg: &PerspNetConfig, b: usize, dev: &Device) -> Result<Batch> {
        let s = cfg.input_size;
        let m = cfg.points;
        let v = cfg.vertices;
        let img = Tensor::randn(0f32, 1., (b, 3, s, s), dev)?;
        let mut choose = Vec::new();
        let mut ids = Vec::new();
        let mut wts = Vec::new();
        for bi in 0..b {
            for i in 0..m {
                choose.push(((i * 13 + bi * 7) % (s * s)) as u32);
                let base = (i * 5 + bi) % (v - 2);
                ids.extend([base as u32, base as u32 + 1, base as u32 + 2]);
                wts.extend([0.5f32, 0.3, 0.2]);
            }
        }
        let choose = Tensor::from_vec(choose, (b, m), dev)?;
        let ids = Tensor::from_vec(ids, (b, m, 3), dev)?;
        let weights = Tensor::from_vec(wts, (b, m, 3), dev)?;
        // A smooth canonical mesh (a function of the vertex UVs), as real faces are.
        let uv = synthetic_vertex_uv(v, dev)?.to_vec2::<f32>()?;
        let mut mv = Vec::with_capacity(b * v * 3);
        for _ in 0..b {
            for p in &uv {
                mv.extend([
                    0.1 * (p[0] - 0.5),
                    0.1 * (p[1] - 0.5),
                    0.05 * (p[0] * 3.0).sin(),
                ]);
            }
        }
        let model = Tensor::from_vec(mv, (b, v, 3), dev)?;
        // Ground-truth coordinates consistent with the barycentric targets (official 4.5 scale).
        let picked = model
            .unsqueeze(1)?
            .broadcast_as((b, m, v, 3))?
            .contiguous()?
            .gather(
                &ids.unsqueeze(3)?.broadcast_as((b, m, 3, 3))?.contiguous()?,
                2,
            )?; // b m 3 3
        let nocs = picked
            .broadcast_mul(&weights.unsqueeze(3)?)?
            .sum(2)?
            .affine(4.5, 0.0)?;
        let mask = Tensor::rand(0f32, 1., (b, s, s), dev)?
            .ge(0.5)?
            .to_dtype(DType::F32)?;
        Ok(Batch {
            img,
            choose,
            nocs,
            model,
            mask,
            ids,
            weights,
        })
    }

    #[test]
    fn loss_pieces_hand_values() -> Result<()> {
        let dev = Device::Cpu;
        // smooth L1: d = 0.005 -> 0.005^2 / 0.02 = 0.00125; d = 0.5 -> 0.495; summed over last axis.
        let p = Tensor::new(&[[0.005f32, 0.5]], &dev)?;
        let z = Tensor::zeros((1, 2), DType::F32, &dev)?;
        let l: f32 = smooth_l1_sum_mean(&p, &z, 0.01)?.to_scalar()?;
        assert!((l - 0.49625).abs() < 1e-6);
        // The paper's plain L1 (threshold 0): 0.005 + 0.5.
        let l: f32 = smooth_l1_sum_mean(&p, &z, 0.0)?.to_scalar()?;
        assert!((l - 0.505).abs() < 1e-6);
        // KL: dense and sparse forms agree.
        let logits = Tensor::randn(0f32, 1., (2, 3, 6), &dev)?;
        let log_p = candle_nn::ops::log_softmax(&logits, 2)?;
        let ids = Tensor::new(
            &[
                [[0u32, 1, 2], [3, 4, 5], [1, 3, 5]],
                [[2u32, 0, 4], [5, 1, 3], [0, 2, 1]],
            ],
            &dev,
        )?;
        let w = Tensor::new(&[[[0.2f32, 0.3, 0.5]; 3]; 2], &dev)?;
        let dense = Tensor::zeros((2, 3, 6), DType::F32, &dev)?.scatter_add(&ids, &w, 2)?;
        let a: f32 = kl_loss(&log_p, &CorrTarget::Dense(dense))?.to_scalar()?;
        let b: f32 = kl_loss(&log_p, &CorrTarget::Sparse { ids, weights: w })?.to_scalar()?;
        assert!((a - b).abs() < 1e-4, "{a} vs {b}");
        assert!(a > 0.0);
        // Segmentation CE with equal logits is ln 2.
        let lg = Tensor::zeros((1, 2, 2, 2), DType::F32, &dev)?;
        let mk = Tensor::new(&[[[0u32, 1], [1, 0]]], &dev)?;
        let ce: f32 = seg_cross_entropy(&lg, &mk)?.to_scalar()?;
        assert!((ce - std::f32::consts::LN_2).abs() < 1e-6);
        // Schedule.
        let mut lw = LossWeights::default();
        lw.update_schedule(0.05);
        assert_eq!((lw.kl, lw.seg, lw.shape), (0.01, 0.01, 1.0));
        lw.update_schedule(0.005);
        assert_eq!((lw.kl, lw.seg, lw.shape, lw.uv), (0.001, 0.01, 0.5, 0.5));
        Ok(())
    }

    #[test]
    fn tiny_overfits_one_batch_and_round_trips() -> Result<()> {
        let dev = Device::Cpu;
        let cfg = PerspNetConfig::tiny();
        let varmap = VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, &dev);
        let uv = synthetic_vertex_uv(cfg.vertices, &dev)?;
        let net = PerspNet::new(&cfg, &uv, vb)?;
        let bt = batch(&cfg, 2, &dev)?;
        let corr = CorrTarget::Sparse {
            ids: bt.ids.clone(),
            weights: bt.weights.clone(),
        };
        let targets = LossTargets {
            nocs: &bt.nocs,
            model: &bt.model,
            seg_mask: &bt.mask,
            corr: &corr,
            uv_map: None,
        };
        // Fixed weights so that the totals are comparable across steps.
        let weights = LossWeights::default();
        let mut opt = AdamW::new(
            trainable_vars(&varmap),
            ParamsAdamW {
                lr: 1e-2,
                weight_decay: 0.0,
                ..Default::default()
            },
        )?;
        let mut totals = Vec::new();
        for step in 0..12 {
            let out = net.forward(&bt.img, &bt.choose, true)?;
            let terms = perspnet_loss(&out, &targets, &weights)?;
            let v = terms.values()?;
            println!(
                "step {step}: total {:.4} corr {:.4} shape {:.4} kl {:.4} ent {:.5} seg {:.4}",
                v[0], v[1], v[2], v[3], v[4], v[5]
            );
            assert!(v.iter().all(|x| x.is_finite()));
            totals.push(v[0]);
            opt.backward_step(&terms.total)?;
        }
        assert!(
            totals[11] < 0.93 * totals[0],
            "loss did not fall: {totals:?}"
        );

        // The stateful loss runs and reports every term.
        let mut loss = PerspNetLoss::default();
        let out = net.forward(&bt.img, &bt.choose, false)?;
        let t = loss.compute(&out, &targets)?;
        assert!(t.values()?.iter().all(|x| x.is_finite()));
        // The paper's variant: L_corr is the plain L1 of X_corr (at the official 4.5 / 9
        // scale) against the targets, computed here from the raw outputs; the weights
        // are the paper's (0.5 / 0.01 / 1 / 0.01), and they stay put even when the weighted
        // L_corr is below the schedule's thresholds (a corr weight of 1e-6 puts it
        // there), where the official loss lowers them.
        let mut paper = PerspNetLoss::new(LossVariant::Paper);
        let tp = paper.compute(&out, &targets)?;
        let coords = out.correspondences()?.affine(0.5, 0.0)?;
        let c = coords.flatten_to(1)?.to_vec2::<f32>()?;
        let n = bt.nocs.flatten_to(1)?.to_vec2::<f32>()?;
        let l1 = c
            .iter()
            .zip(&n)
            .map(|(a, b)| a.iter().zip(b).map(|(x, y)| (x - y).abs()).sum::<f32>())
            .sum::<f32>()
            / c.len() as f32;
        let (vp, vo) = (tp.values()?, t.values()?);
        assert!((vp[1] - l1).abs() < 1e-5 * l1.max(1.0), "{} vs {l1}", vp[1]);
        assert!(
            vp[1] > vo[1],
            "L1 {} is above the smooth L1 {}",
            vp[1],
            vo[1]
        );
        assert_eq!(paper.weights, LossWeights::paper());
        let mut low = PerspNetLoss::new(LossVariant::Paper);
        low.weights.corr = 1e-6;
        low.compute(&out, &targets)?;
        assert_eq!(low.weights.kl, LossWeights::paper().kl);
        let mut official_low = PerspNetLoss::default();
        official_low.weights.corr = 1e-6;
        official_low.compute(&out, &targets)?;
        assert_ne!(official_low.weights.kl, LossWeights::default().kl);

        // Save / load round trip (eval outputs identical).
        let path =
            std::env::temp_dir().join(format!("perspnet_tiny_{}.safetensors", std::process::id()));
        varmap.save(&path)?;
        let mut varmap2 = VarMap::new();
        let vb2 = VarBuilder::from_varmap(&varmap2, DType::F32, &dev);
        let net2 = PerspNet::new(&cfg, &uv, vb2)?;
        varmap2.load(&path)?;
        let a = net.forward(&bt.img, &bt.choose, false)?;
        let b = net2.forward(&bt.img, &bt.choose, false)?;
        let d1: f32 = (&a.assign_logits - &b.assign_logits)?
            .abs()?
            .max_all()?
            .to_scalar()?;
        let d2: f32 = (&a.dense.uv_map - &b.dense.uv_map)?
            .abs()?
            .max_all()?
            .to_scalar()?;
        assert_eq!((d1, d2), (0.0, 0.0));
        std::fs::remove_file(&path).ok();
        Ok(())
    }
}

mod ablations {
    //! "w/o PE": without the position encoding, points whose image features are equal
    //! get equal assignment rows; with it they differ by position.

    use arkit_perspnet::synthetic_vertex_uv;
    use arkit_perspnet::{PerspNet, PerspNetConfig};
    use candle_core::{DType, Device, Result, Tensor};
    use candle_nn::{VarBuilder, VarMap};

    /// The largest difference between any assignment row and the first, with the
    /// point-wise image-feature layer zeroed (so every point's image feature is 0).
    fn row_spread(position_encoding: bool) -> Result<f32> {
        let dev = Device::Cpu;
        let cfg = PerspNetConfig {
            position_encoding,
            ..PerspNetConfig::tiny()
        };
        let vm = VarMap::new();
        let vb = VarBuilder::from_varmap(&vm, DType::F32, &dev);
        let net = PerspNet::new(&cfg, &synthetic_vertex_uv(cfg.vertices, &dev)?, vb)?;
        {
            let data = vm.data().lock().unwrap();
            for (k, v) in data.iter() {
                if k.starts_with("instance_color.") {
                    v.set(&v.zeros_like()?)?;
                }
            }
            let w = data["instance_global.0.weight"].dims().to_vec();
            assert_eq!(w[1], cfg.local_channels());
        }
        let s = cfg.input_size;
        let img = Tensor::randn(0f32, 1., (1, 3, s, s), &dev)?;
        let choose: Vec<u32> = (0..cfg.points as u32)
            .map(|i| (i * 37) % (s * s) as u32)
            .collect();
        let choose = Tensor::from_vec(choose, (1, cfg.points), &dev)?;
        let a = net
            .forward(&img, &choose, false)?
            .assign_logits
            .squeeze(0)?;
        let first = a.narrow(0, 0, 1)?;
        a.broadcast_sub(&first)?
            .abs()?
            .max_all()?
            .to_scalar::<f32>()
    }

    #[test]
    fn without_position_encoding_rows_depend_on_features_only() -> Result<()> {
        assert_eq!(row_spread(false)?, 0.0);
        assert!(row_spread(true)? > 1e-4);
        let mut c = PerspNetConfig::paper();
        c.position_encoding = false;
        assert_eq!(c.assign_in_channels(), 64 + 2048);
        Ok(())
    }
}

mod pipeline {
    //! synth -> convert -> render (64x64, 256 points) -> train (tiny) -> predict
    //! --model -> eval, on a few samples.

    use arkit_core::conventions::Camera;
    use arkit_data::eval::EvalOptions;
    use arkit_data::ingest::synth::{self, FaceSource, SynthOptions};
    use arkit_data::ingest::{self, ConvertOptions, ValidationContext};
    use arkit_data::pose::RansacParams;
    use arkit_data::render::FaceRenderer;
    use arkit_data::render::RenderOptions;
    use arkit_perspnet::PerspNetConfig;
    use arkit_perspnet::TrainOptions;
    use candle_core::Device;

    #[test]
    fn train_tiny_then_predict_and_evaluate() {
        let release = tempfile::tempdir().unwrap();
        let options = SynthOptions {
            subjects: 2,
            images_per_subject: 3,
            width: 256,
            height: 256,
            seed: 8,
            ..SynthOptions::default()
        };
        synth::generate(&FaceSource::builtin(), &options, release.path(), &|| {}).unwrap();
        let topology = arkit_data::mesh::builtin().topology.clone();
        let dir = tempfile::tempdir().unwrap();
        let ctx = ValidationContext {
            projection: Camera::release_projection(),
            topology: topology.clone(),
            embed_images: false,
        };
        let copts = ConvertOptions {
            input: release.path().to_path_buf(),
            output: dir.path().to_path_buf(),
            resources: None,
            rows_per_shard: 100,
            embed_images: false,
            shard_index: 0,
            shard_count: 1,
            overwrite: false,
        };
        ingest::convert(&copts, &ctx, &|_| {}).unwrap();
        let cfg = PerspNetConfig::tiny();
        // Targets at the wrong size are refused with the render options to use.
        let renderer = FaceRenderer::new(topology.clone(), Camera::release_projection()).unwrap();
        let wrong = tempfile::tempdir().unwrap();
        let ro = |size: u32, out: &std::path::Path| RenderOptions {
            size,
            uv_size: 16,
            points: 256,
            seed: 1,
            shard: (0, 1),
            full_mask: false,
            output: out.to_path_buf(),
        };
        arkit_data::render::render_dataset(dir.path(), &renderer, &ro(96, wrong.path()), &|_| {})
            .unwrap();
        let e = match arkit_perspnet::read_examples(dir.path(), wrong.path(), &cfg, None) {
            Err(e) => e.to_string(),
            Ok(_) => panic!("targets at 96 accepted for a 64 network"),
        };
        assert!(e.contains("--size 64"), "{e}");
        arkit_data::render::render_dataset(dir.path(), &renderer, &ro(64, dir.path()), &|_| {})
            .unwrap();
        let examples = arkit_perspnet::read_examples(dir.path(), dir.path(), &cfg, None).unwrap();
        assert_eq!(examples.len(), 6);
        // The stored coordinates are the official 4.5x scale of the mesh at the weights.
        let e0 = &examples[0];
        let mut c = [0f32; 3];
        for k in 0..3 {
            let v = e0.ids[k] as usize;
            for (a, ca) in c.iter_mut().enumerate() {
                *ca += e0.weights[k] * e0.sample.verts[3 * v + a];
            }
        }
        for (n, ca) in e0.nocs.iter().zip(c) {
            assert!((n - 4.5 * ca).abs() < 1e-5);
        }
        // Overfit four samples: the loss falls.
        let model_dir = tempfile::tempdir().unwrap();
        let topts = TrainOptions {
            config: cfg.clone(),
            epochs: 8,
            max_steps: None,
            batch: 4,
            learning_rate: 5e-3,
            lr_hold: 0.5,
            augmentation: arkit_perspnet::Augmentation::DEFAULT,
            seed: 3,
            resume: false,
            lowered_start: false,
            output: model_dir.path().to_path_buf(),
        };
        let (ck, log) = arkit_perspnet::train(&examples[..4], &topology, &topts, &|_| {}).unwrap();
        assert_eq!(ck.steps, 8);
        let first = log[0].total;
        let last = log
            .iter()
            .rev()
            .take(2)
            .map(|s| s.total)
            .fold(f32::MAX, f32::min);
        assert!(last < first, "loss {first} -> {last}");
        for f in ["perspnet.json", "model.safetensors", "loss.csv"] {
            assert!(model_dir.path().join(f).exists(), "{f}");
        }
        // Interrupted after epoch 4 (a panic in the progress callback at step 5), then
        // resumed: the checkpoint written after epoch 4 (weights, Adam's moments, loss
        // weights) carries the run on, so every step's loss and the final weights equal
        // the uninterrupted run's exactly (with the moments restarted at zero, steps
        // 5-7 and the weights differ).
        let cut = tempfile::tempdir().unwrap();
        let cut_opts = TrainOptions {
            output: cut.path().to_path_buf(),
            ..topts.clone()
        };
        let interrupted = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            arkit_perspnet::train(&examples[..4], &topology, &cut_opts, &|s| {
                assert!(s.step < 4, "interrupted");
            })
        }));
        assert!(interrupted.is_err());
        // A new folder holding a copy of each file of `d`.
        let copy_of = |d: &std::path::Path| {
            let copy = tempfile::tempdir().unwrap();
            for f in std::fs::read_dir(d).unwrap() {
                let f = f.unwrap().path();
                std::fs::copy(&f, copy.path().join(f.file_name().unwrap())).unwrap();
            }
            copy
        };
        // The checkpoint of epoch 4, kept for the torn-checkpoint case below.
        let torn = copy_of(cut.path());
        let resumed_opts = TrainOptions {
            resume: true,
            ..cut_opts.clone()
        };
        let (rck, rlog) =
            arkit_perspnet::train(&examples[..4], &topology, &resumed_opts, &|_| {}).unwrap();
        assert_eq!((rck.steps, rck.epochs_done), (8, 8));
        assert_eq!(rlog.len(), 8);
        for k in 0..8 {
            assert_eq!(rlog[k].total, log[k].total, "step {k}");
        }
        let weights = |d: &std::path::Path| {
            let mut t: Vec<(String, Vec<f32>)> =
                candle_core::safetensors::load(d.join("model.safetensors"), &Device::Cpu)
                    .unwrap()
                    .into_iter()
                    .map(|(k, v)| (k, v.flatten_all().unwrap().to_vec1::<f32>().unwrap()))
                    .collect();
            t.sort_by(|a, b| a.0.cmp(&b.0));
            t
        };
        assert_eq!(weights(cut.path()), weights(model_dir.path()));
        assert!(cut.path().join(arkit_perspnet::ADAM_FILE).exists());
        // Torn: what a kill between two renames leaves (the weights of epoch 8, the
        // rest of epoch 4). --resume refuses it, naming the file and what differs, and
        // leaves every file as it was; so it does without the record of the files.
        std::fs::copy(
            model_dir.path().join("model.safetensors"),
            torn.path().join("model.safetensors"),
        )
        .unwrap();
        let snapshot = |d: &std::path::Path| {
            let mut v: Vec<(std::ffi::OsString, Vec<u8>)> = std::fs::read_dir(d)
                .unwrap()
                .map(|f| f.unwrap().path())
                .map(|f| {
                    (
                        f.file_name().unwrap().to_owned(),
                        std::fs::read(&f).unwrap(),
                    )
                })
                .collect();
            v.sort();
            v
        };
        // `--resume` into `dir`, which must be refused (`what` it holds): the error.
        let refused = |dir: &std::path::Path, what: &str| {
            let opts = TrainOptions {
                output: dir.to_path_buf(),
                ..resumed_opts.clone()
            };
            match arkit_perspnet::train(&examples[..4], &topology, &opts, &|_| {}) {
                Err(e) => e.to_string(),
                Ok(_) => panic!("{what} was resumed"),
            }
        };
        let before = snapshot(torn.path());
        let e = refused(torn.path(), "a torn checkpoint");
        assert!(
            e.contains("model.safetensors: its SHA-256 is")
                && e.contains("checkpoint.json records")
                && e.contains("torn"),
            "{e}"
        );
        assert!(
            snapshot(torn.path()) == before,
            "the refused checkpoint was changed"
        );
        // Prediction and export refuse the torn folder too (epoch 8's weights beside
        // epoch 4's config), naming the weights; the whole folders load.
        let load_err = |dir: &std::path::Path| match arkit_perspnet::load(dir, &topology) {
            Err(e) => e.to_string(),
            Ok(_) => panic!("{} was loaded", dir.display()),
        };
        let e = load_err(torn.path());
        assert!(
            e.contains("model.safetensors: its SHA-256 is")
                && e.contains("checkpoint.json records")
                && e.contains("the model folder is torn"),
            "{e}"
        );
        let w = torn.path().join("exported.safetensors");
        let e = arkit_perspnet::export_weights(torn.path(), &w)
            .expect_err("the torn folder was exported")
            .to_string();
        assert!(e.contains("model.safetensors: its SHA-256 is"), "{e}");
        assert!(!w.exists());
        arkit_perspnet::load(cut.path(), &topology).unwrap();
        arkit_perspnet::load(model_dir.path(), &topology).unwrap();
        std::fs::remove_file(torn.path().join(arkit_perspnet::CHECKPOINT_RECORD)).unwrap();
        // Without a record (a folder from before records were kept) the folder is read
        // as it is: nothing tells its files apart any more.
        arkit_perspnet::load(torn.path(), &topology).unwrap();
        let e = refused(torn.path(), "a checkpoint without its record");
        assert!(e.contains("checkpoint.json: cannot be read"), "{e}");
        // A whole checkpoint less its `perspnet.json`: refused, naming that file, and
        // left as it is (it was trained over, from new weights, before).
        let no_config = copy_of(cut.path());
        std::fs::remove_file(no_config.path().join("perspnet.json")).unwrap();
        let before = snapshot(no_config.path());
        let e = refused(no_config.path(), "a checkpoint without its perspnet.json");
        assert!(
            e.contains("perspnet.json: missing") && e.contains("torn"),
            "{e}"
        );
        assert!(
            snapshot(no_config.path()) == before,
            "the refused checkpoint was changed"
        );
        // A loss log cut short: its size differs.
        let cut2 = copy_of(cut.path());
        let csv = std::fs::read(cut2.path().join("loss.csv")).unwrap();
        std::fs::write(cut2.path().join("loss.csv"), &csv[..csv.len() - 10]).unwrap();
        let e = refused(cut2.path(), "a checkpoint with a cut loss log");
        assert!(
            e.contains(&format!(
                "loss.csv: {} bytes, but checkpoint.json records {}",
                csv.len() - 10,
                csv.len()
            )),
            "{e}"
        );
        // A step budget stops part way through an epoch; until then it is the same
        // run (the rate is still held), and a budget the epochs cannot cover is refused.
        let budget = tempfile::tempdir().unwrap();
        let budget_opts = TrainOptions {
            output: budget.path().to_path_buf(),
            max_steps: Some(3),
            ..topts.clone()
        };
        let (bck, blog) =
            arkit_perspnet::train(&examples[..4], &topology, &budget_opts, &|_| {}).unwrap();
        assert_eq!((bck.steps, blog.len(), bck.max_steps), (3, 3, Some(3)));
        assert_eq!(blog[0].total, log[0].total);
        let too_many = TrainOptions {
            max_steps: Some(1000),
            ..budget_opts
        };
        assert!(arkit_perspnet::train(&examples[..4], &topology, &too_many, &|_| {}).is_err());
        // Other settings are refused rather than mixed in.
        let other = TrainOptions {
            learning_rate: 1e-3,
            ..resumed_opts
        };
        let e = match arkit_perspnet::train(&examples[..4], &topology, &other, &|_| {}) {
            Err(e) => e.to_string(),
            Ok(_) => panic!("resumed with another learning rate"),
        };
        assert!(e.contains("other settings"), "{e}");
        // Load, predict (deterministic), evaluate.
        let model = arkit_perspnet::load(model_dir.path(), &topology).unwrap();
        let run_with = |rule| {
            arkit_perspnet::model_predictions(
                dir.path(),
                &model,
                None,
                rule,
                None,
                5,
                &RansacParams::default(),
                &|_| {},
            )
            .unwrap()
        };
        let run = || run_with(arkit_data::crop::RuleSet::Exact);
        let (a, sa) = run();
        let (b, _) = run();
        assert_eq!(a, b);
        // The official crop is another input: the same samples, other predictions.
        let (c, sc) = run_with(arkit_data::crop::RuleSet::Official);
        assert_eq!(sc.samples, 6);
        assert!(a.iter().zip(&c).all(|(p, q)| p.key == q.key));
        assert_ne!(a, c);
        assert_eq!(sa.samples, 6);
        assert!(a.iter().all(|p| p.verts.as_ref().unwrap().len() == 3660));
        let options = EvalOptions {
            split: None,
            ..EvalOptions::default()
        };
        let ev = arkit_data::eval::evaluate(dir.path(), &a, &options).unwrap();
        assert_eq!(ev.summary.samples, 6);
        assert!(ev.summary.recon_mean_mm.unwrap().is_finite());
        assert!(
            ev.summary.mask.is_some(),
            "{:?}",
            ev.problems.unscored_masks
        );

        // The same network on BIWI (convert --format biwi): crops around the BIWI
        // mesh's 68 landmarks, poses through PnP, eval's ADD on the subject's head; the
        // predicted 1,220-vertex meshes are not scored against the 6,918-vertex heads.
        let hpdb = tempfile::tempdir().unwrap();
        crate::support::biwi_writer::write_hpdb(hpdb.path());
        let biwi_pq = tempfile::tempdir().unwrap();
        let staging = biwi_pq.path().join("biwi-release");
        let (staged, biwi_topology) =
            arkit_data::ingest::biwi::stage(hpdb.path(), &staging, 256, &|| {}).unwrap();
        assert_eq!(staged.staged, 6);
        let bctx = ValidationContext {
            projection: Camera::release_projection(),
            topology: biwi_topology,
            embed_images: false,
        };
        let bopts = ConvertOptions {
            input: staging.clone(),
            output: biwi_pq.path().to_path_buf(),
            ..copts.clone()
        };
        let m = ingest::convert(&bopts, &bctx, &|_| {}).unwrap();
        assert_eq!((m.converted, m.skipped), (6, 0));
        let (rows, summary) = arkit_perspnet::model_predictions(
            biwi_pq.path(),
            &model,
            None,
            arkit_data::crop::RuleSet::Exact,
            None,
            5,
            &RansacParams::default(),
            &|_| {},
        )
        .unwrap();
        assert_eq!(summary.samples, 6);
        assert_eq!(rows.len(), 6);
        let ev = arkit_data::eval::evaluate(
            biwi_pq.path(),
            &rows,
            &EvalOptions {
                split: None,
                ..EvalOptions::default()
            },
        )
        .unwrap();
        assert_eq!(ev.summary.samples, 6);
        assert!(ev.summary.add_mm.is_finite());
        assert_eq!(ev.summary.recon_mean_mm, None);
        assert_eq!(
            ev.problems.unscored_verts,
            rows.iter().filter(|r| r.verts.is_some()).count()
        );
    }
}
