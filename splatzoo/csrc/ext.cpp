// Torch bindings of the native tile rasterizer: forward(...) and backward(...) on CPU tensors, and on CUDA tensors
// when built with SPLATZOO_WITH_CUDA. splatzoo/rasterizers/native.py wraps them in a torch.autograd.Function.
#include <torch/extension.h>

#include <climits>
#include <optional>

#include "rasterize.h"
#include "surfel_math.h"

#ifdef SPLATZOO_WITH_CUDA
#include <c10/cuda/CUDAStream.h>
#endif

namespace {

using at::Tensor;

// Inputs in the order of the Python call; all [M,...] of one floating dtype on one device.
struct Inputs {
    Tensor T, center, depth, normal, opac, base, wv, wp, wa, boxes;
    Tensor wc;  // int32 [M] waves in use per surfel, or undefined: all K
    int64_t M, K, W, H;
};

Inputs check_inputs(const Tensor& T, const Tensor& center, const Tensor& depth, const Tensor& normal,
                    const Tensor& opac, const Tensor& base, const Tensor& wv, const Tensor& wp, const Tensor& wa,
                    const Tensor& boxes, int64_t W, int64_t H, const std::optional<Tensor>& wave_counts) {
    const int64_t M = T.size(0);
    const int64_t K = wv.dim() == 3 ? wv.size(1) : -1;
    auto want = [&](const Tensor& t, std::vector<int64_t> shape, const char* name) {
        TORCH_CHECK(t.sizes().vec() == shape, "splatzoo native rasterizer: ", name, " must have shape ", at::IntArrayRef(shape),
                    ", got ", t.sizes());
        TORCH_CHECK(t.scalar_type() == T.scalar_type() && t.device() == T.device(), "splatzoo native rasterizer: ", name,
                    " must be ", T.scalar_type(), " on ", T.device(), " like T");
    };
    TORCH_CHECK(T.scalar_type() == at::kFloat || T.scalar_type() == at::kDouble,
                "splatzoo native rasterizer: float32 or float64 tensors expected, got ", T.scalar_type());
    TORCH_CHECK(K >= 0, "splatzoo native rasterizer: wave_vectors must be [M,K,2]");
    TORCH_CHECK(W >= 1 && H >= 1 && W <= (1 << 20) && H <= (1 << 20), "splatzoo native rasterizer: bad image size ", W, "x", H);
    TORCH_CHECK(M < INT_MAX, "splatzoo native rasterizer: too many surfels");
    want(T, {M, 3, 3}, "T");
    want(center, {M, 2}, "center_px");
    want(depth, {M}, "depth");
    want(normal, {M, 3}, "normal");
    want(opac, {M}, "opacities");
    want(base, {M, 3}, "base_color");
    want(wv, {M, K, 2}, "wave_vectors");
    want(wp, {M, K}, "wave_phases");
    want(wa, {M, K, 3}, "wave_amplitudes");
    want(boxes, {M, 4}, "boxes");
    Tensor wc;
    if (wave_counts.has_value() && wave_counts->defined()) {
        wc = *wave_counts;
        TORCH_CHECK(wc.scalar_type() == at::kInt && wc.device() == T.device() && wc.sizes().vec() == std::vector<int64_t>{M},
                    "splatzoo native rasterizer: wave_counts must be int32 [", M, "] on ", T.device(), ", got ",
                    wc.scalar_type(), " ", wc.sizes(), " on ", wc.device());
        wc = wc.contiguous();
        if (M > 0 && wc.device().is_cpu()) {  // an out-of-range count would read past the surfel's row
            TORCH_CHECK(wc.min().item<int>() >= 0 && wc.max().item<int>() <= K,
                        "splatzoo native rasterizer: wave_counts must lie in [0, K=", K, "]");
        }
    }
    return {T.contiguous(), center.contiguous(), depth.contiguous(), normal.contiguous(), opac.contiguous(),
            base.contiguous(), wv.contiguous(), wp.contiguous(), wa.contiguous(), boxes.contiguous(), wc, M, K, W, H};
}

template <class S>
sz::SurfelArgs<S> surfel_args(const Inputs& in) {
    return {int(in.M), int(in.K), int(in.W), int(in.H),
            in.T.data_ptr<S>(), in.center.data_ptr<S>(), in.depth.data_ptr<S>(), in.normal.data_ptr<S>(),
            in.opac.data_ptr<S>(), in.base.data_ptr<S>(), in.wv.data_ptr<S>(), in.wp.data_ptr<S>(),
            in.wa.data_ptr<S>(), in.boxes.data_ptr<S>(), in.wc.defined() ? in.wc.data_ptr<int>() : nullptr};
}

// Outputs and saved state, in the order returned to Python.
enum : int { O_RGB, O_ALPHA, O_DEPTH, O_MEDIAN, O_NORMAL, O_DIST, S_TFINAL, S_TOT, S_LAST, S_MED, S_GEOM, S_BOUNDS,
             S_TILE_START, S_TILE_LIST, S_PAIR_POS, S_SURFEL_OFF, N_OUT };

template <class S>
sz::FrameArgs<S> frame_args(std::vector<Tensor>& o) {
    return {o[S_GEOM].data_ptr<S>(), o[S_BOUNDS].data_ptr<int>(), o[S_TILE_START].data_ptr<int>(),
            o[S_TILE_LIST].data_ptr<int>(), o[O_RGB].data_ptr<S>(), o[O_ALPHA].data_ptr<S>(),
            o[O_DEPTH].data_ptr<S>(), o[O_MEDIAN].data_ptr<S>(), o[O_NORMAL].data_ptr<S>(),
            o[O_DIST].data_ptr<S>(), o[S_TFINAL].data_ptr<S>(), o[S_TOT].data_ptr<S>(),
            o[S_LAST].data_ptr<int>(), o[S_MED].data_ptr<int>()};
}

std::vector<Tensor> alloc_outputs(const Inputs& in) {
    auto f = in.T.options();
    auto i32 = f.dtype(at::kInt);
    const int64_t H = in.H, W = in.W;
    std::vector<Tensor> o(N_OUT);
    o[O_RGB] = at::empty({H, W, 3}, f);
    o[O_ALPHA] = at::empty({H, W}, f);
    o[O_DEPTH] = at::empty({H, W}, f);
    o[O_MEDIAN] = at::empty({H, W}, f);
    o[O_NORMAL] = at::empty({H, W, 3}, f);
    o[O_DIST] = at::empty({H, W}, f);
    o[S_TFINAL] = at::empty({H, W}, f);
    o[S_TOT] = at::empty({H, W, 3}, f);
    o[S_LAST] = at::empty({H, W}, i32);
    o[S_MED] = at::empty({H, W}, i32);
    o[S_GEOM] = at::empty({in.M, sz::GEOM}, f);
    o[S_BOUNDS] = at::empty({in.M, 4}, i32);
    o[S_TILE_START] = at::empty({int64_t(sz::tiles_x(int(W))) * sz::tiles_y(int(H)) + 1}, i32);
    return o;
}

std::vector<Tensor> forward_cpu(const Inputs& in) {
    std::vector<Tensor> o = alloc_outputs(in);
    const int threads = at::get_num_threads();
    o[S_SURFEL_OFF] = at::empty({in.M + 1}, in.T.options().dtype(at::kLong));
    AT_DISPATCH_FLOATING_TYPES(in.T.scalar_type(), "splatzoo_forward_cpu", [&] {
        auto s = surfel_args<scalar_t>(in);
        const int64_t P = sz::cpu_prepare<scalar_t>(s, o[S_GEOM].data_ptr<scalar_t>(), o[S_BOUNDS].data_ptr<int>(),
                                                     o[S_SURFEL_OFF].data_ptr<int64_t>(), threads);
        TORCH_CHECK(P < INT_MAX, "splatzoo native rasterizer: ", P,
                    " (tile, surfel) pairs exceed 2^31; render at a lower resolution or with fewer/smaller surfels");
        auto i32 = in.T.options().dtype(at::kInt);
        o[S_TILE_LIST] = at::empty({P}, i32);
        o[S_PAIR_POS] = at::empty({P}, i32);
        sz::cpu_bin(int(in.M), int(in.W), int(in.H), o[S_BOUNDS].data_ptr<int>(), o[S_SURFEL_OFF].data_ptr<int64_t>(),
                    o[S_TILE_START].data_ptr<int>(), o[S_TILE_LIST].data_ptr<int>(), o[S_PAIR_POS].data_ptr<int>());
        sz::cpu_forward<scalar_t>(s, frame_args<scalar_t>(o), threads);
    });
    return o;
}

#ifdef SPLATZOO_WITH_CUDA
std::vector<Tensor> forward_cuda(const Inputs& in) {
    std::vector<Tensor> o = alloc_outputs(in);
    void* stream = c10::cuda::getCurrentCUDAStream().stream();
    auto i64 = in.T.options().dtype(at::kLong);
    Tensor count = at::empty({in.M}, in.T.options().dtype(at::kInt));
    AT_DISPATCH_FLOATING_TYPES(in.T.scalar_type(), "splatzoo_prepare_cuda", [&] {
        sz::cuda_prepare<scalar_t>(surfel_args<scalar_t>(in), o[S_GEOM].data_ptr<scalar_t>(),
                                   o[S_BOUNDS].data_ptr<int>(), count.data_ptr<int>(), stream);
    });
    // Binning with ATen ops: one key tile * M + surfel per pair, sorted; surfel order is depth order.
    const int64_t ntx = sz::tiles_x(int(in.W)), nt = ntx * sz::tiles_y(int(in.H));
    Tensor count64 = count.to(at::kLong);
    Tensor offsets = at::cumsum(count64, 0);
    const int64_t P = in.M ? offsets[-1].item<int64_t>() : 0;
    TORCH_CHECK(P < INT_MAX, "splatzoo native rasterizer: ", P, " (tile, surfel) pairs exceed 2^31");
    if (P > 0) {
        Tensor pair_surfel = at::repeat_interleave(at::arange(in.M, i64), count64, 0, P);
        Tensor local = at::arange(P, i64) - (offsets - count64).index_select(0, pair_surfel);
        Tensor b = o[S_BOUNDS].to(at::kLong).index_select(0, pair_surfel);
        Tensor tx0 = at::floor_divide(b.select(1, 0), sz::TILE), tx1 = at::floor_divide(b.select(1, 1), sz::TILE);
        Tensor ty0 = at::floor_divide(b.select(1, 2), sz::TILE);
        Tensor wt = tx1 - tx0 + 1;
        Tensor tile = (ty0 + at::floor_divide(local, wt)) * ntx + tx0 + at::remainder(local, wt);
        Tensor key = std::get<0>(at::sort(tile * in.M + pair_surfel));
        o[S_TILE_LIST] = at::remainder(key, in.M).to(at::kInt);
        o[S_TILE_START] = at::searchsorted(at::floor_divide(key, in.M), at::arange(nt + 1, i64)).to(at::kInt);
    } else {
        o[S_TILE_LIST] = at::empty({0}, in.T.options().dtype(at::kInt));
        o[S_TILE_START].zero_();
    }
    o[S_PAIR_POS] = at::empty({0}, in.T.options().dtype(at::kInt));
    o[S_SURFEL_OFF] = at::empty({0}, i64);
    AT_DISPATCH_FLOATING_TYPES(in.T.scalar_type(), "splatzoo_forward_cuda", [&] {
        sz::cuda_forward<scalar_t>(surfel_args<scalar_t>(in), frame_args<scalar_t>(o), stream);
    });
    return o;
}
#endif

// forward(T, center_px, depth, normal, opacities, base_color, wave_vectors, wave_phases, wave_amplitudes, boxes,
//         width, height, wave_counts=None) -> [rgb, alpha, depth, median_depth, normal, distortion, *saved]
std::vector<Tensor> forward(const Tensor& T, const Tensor& center, const Tensor& depth, const Tensor& normal,
                            const Tensor& opac, const Tensor& base, const Tensor& wv, const Tensor& wp,
                            const Tensor& wa, const Tensor& boxes, int64_t W, int64_t H,
                            const std::optional<Tensor>& wave_counts) {
    Inputs in = check_inputs(T, center, depth, normal, opac, base, wv, wp, wa, boxes, W, H, wave_counts);
    if (T.is_cuda()) {
#ifdef SPLATZOO_WITH_CUDA
        return forward_cuda(in);
#else
        TORCH_CHECK(false, "splatzoo native rasterizer: this build has no CUDA support");
#endif
    }
    TORCH_CHECK(T.device().is_cpu(), "splatzoo native rasterizer: unsupported device ", T.device());
    return forward_cpu(in);
}

// backward(inputs..., width, height, saved (10 tensors from forward, S_TFINAL..), grads of the 6 outputs,
//          wave_counts=None) (gradients of waves a surfel does not use are 0)
// -> [v_T, v_center, v_depth, v_normal, v_opacities, v_base, v_wave_vectors, v_wave_phases, v_wave_amplitudes]
std::vector<Tensor> backward(const Tensor& T, const Tensor& center, const Tensor& depth, const Tensor& normal,
                             const Tensor& opac, const Tensor& base, const Tensor& wv, const Tensor& wp,
                             const Tensor& wa, const Tensor& boxes, int64_t W, int64_t H, std::vector<Tensor> outs,
                             std::vector<Tensor> grads, const std::optional<Tensor>& wave_counts) {
    Inputs in = check_inputs(T, center, depth, normal, opac, base, wv, wp, wa, boxes, W, H, wave_counts);
    TORCH_CHECK(int(outs.size()) == N_OUT && grads.size() == 6, "splatzoo native rasterizer: backward got ",
                outs.size(), " saved tensors and ", grads.size(), " gradients");
    for (auto& g : grads) g = g.to(T.scalar_type()).contiguous();
    std::vector<Tensor> v = {at::empty_like(in.T), at::empty_like(in.center), at::empty_like(in.depth),
                             at::empty_like(in.normal), at::empty_like(in.opac), at::empty_like(in.base),
                             at::empty_like(in.wv), at::empty_like(in.wp), at::empty_like(in.wa)};
    if (in.M == 0) return v;
    const int GW = sz::grad_width(int(in.K));
    AT_DISPATCH_FLOATING_TYPES(T.scalar_type(), "splatzoo_backward", [&] {
        auto s = surfel_args<scalar_t>(in);
        auto f = frame_args<scalar_t>(outs);
        sz::GradArgs<scalar_t> g{grads[0].data_ptr<scalar_t>(), grads[1].data_ptr<scalar_t>(),
                                 grads[2].data_ptr<scalar_t>(), grads[3].data_ptr<scalar_t>(),
                                 grads[4].data_ptr<scalar_t>(), grads[5].data_ptr<scalar_t>(),
                                 v[0].data_ptr<scalar_t>(), v[1].data_ptr<scalar_t>(), v[2].data_ptr<scalar_t>(),
                                 v[3].data_ptr<scalar_t>(), v[4].data_ptr<scalar_t>(), v[5].data_ptr<scalar_t>(),
                                 v[6].data_ptr<scalar_t>(), v[7].data_ptr<scalar_t>(), v[8].data_ptr<scalar_t>()};
        if (T.is_cuda()) {
#ifdef SPLATZOO_WITH_CUDA
            Tensor gbuf = at::zeros({in.M, GW}, in.T.options());
            sz::cuda_backward<scalar_t>(s, f, g, gbuf.data_ptr<scalar_t>(),
                                        c10::cuda::getCurrentCUDAStream().stream());
#else
            TORCH_CHECK(false, "splatzoo native rasterizer: this build has no CUDA support");
#endif
        } else {
            const int64_t P = outs[S_TILE_LIST].numel();
            Tensor partials = at::empty({P, GW}, in.T.options());
            sz::cpu_backward<scalar_t>(s, f, g, outs[S_SURFEL_OFF].data_ptr<int64_t>(),
                                       outs[S_PAIR_POS].data_ptr<int>(), partials.data_ptr<scalar_t>(),
                                       at::get_num_threads());
        }
    });
    return v;
}

// ---- the whole CPU render in one call: projection, culling, depth sort, tile rasterizer ------------------------
// Moves the per-surfel set-up (common.project, common.screen_boxes, the sort and the gathers, and their autograd)
// out of Python, where its ~100 small tensor ops cost as much as the tile loop on small images.

template <class S>
sz::CameraArgs<S> camera_args(const Tensor& KR, const Tensor& Kt, const Tensor& eye, int64_t W, int64_t H) {
    sz::CameraArgs<S> c;
    Tensor kr = KR.contiguous(), kt = Kt.contiguous(), e = eye.contiguous();
    for (int i = 0; i < 9; ++i) c.KR[i] = kr.data_ptr<S>()[i];
    for (int i = 0; i < 3; ++i) {
        c.Kt[i] = kt.data_ptr<S>()[i];
        c.eye[i] = e.data_ptr<S>()[i];
    }
    c.W = int(W);
    c.H = int(H);
    return c;
}

void check_camera(const Tensor& means, const Tensor& KR, const Tensor& Kt, const Tensor& eye) {
    TORCH_CHECK(means.device().is_cpu(), "splatzoo render: CPU tensors expected");
    TORCH_CHECK(means.scalar_type() == at::kFloat || means.scalar_type() == at::kDouble,
                "splatzoo render: float32 or float64 tensors expected, got ", means.scalar_type());
    TORCH_CHECK(means.dim() == 2 && means.size(1) == 3, "splatzoo render: means must be [N,3]");
    for (const Tensor* t : {&KR, &Kt, &eye})
        TORCH_CHECK(t->scalar_type() == means.scalar_type() && t->device().is_cpu(),
                    "splatzoo render: camera tensors must be ", means.scalar_type(), " on the CPU");
    TORCH_CHECK(KR.numel() == 9 && Kt.numel() == 3 && eye.numel() == 3, "splatzoo render: KR [3,3], Kt [3], eye [3]");
}

// render(means, quats, scales, opacities, base_color, wave_vectors, wave_phases, wave_amplitudes, KR, Kt, eye,
//        width, height, wave_counts=None)
// -> [rgb, alpha, depth, median_depth, normal, distortion, *saved (N_OUT - 6), T, center, depth, normal, opacities,
//     base, wave_vectors, wave_phases, wave_amplitudes, boxes, wave_counts (compact, or empty), order]
// The compact tensors hold the visible surfels front to back; order maps them to input rows.
std::vector<Tensor> render(const Tensor& means, const Tensor& quats, const Tensor& scales, const Tensor& opac,
                           const Tensor& base, const Tensor& wv, const Tensor& wp, const Tensor& wa, const Tensor& KR,
                           const Tensor& Kt, const Tensor& eye, int64_t W, int64_t H,
                           const std::optional<Tensor>& wave_counts) {
    check_camera(means, KR, Kt, eye);
    const int64_t N = means.size(0);
    TORCH_CHECK(quats.sizes() == at::IntArrayRef({N, 4}) && scales.sizes() == at::IntArrayRef({N, 2}) &&
                    opac.sizes() == at::IntArrayRef({N}),
                "splatzoo render: quats [N,4], scales [N,2], opacities [N] expected");
    for (const Tensor* t : {&quats, &scales, &opac})
        TORCH_CHECK(t->scalar_type() == means.scalar_type() && t->device().is_cpu(),
                    "splatzoo render: every surfel tensor must be ", means.scalar_type(), " on the CPU");
    auto f = means.options();
    Tensor T = at::empty({N, 3, 3}, f), center = at::empty({N, 2}, f), depth = at::empty({N}, f);
    Tensor normal = at::empty({N, 3}, f), boxes = at::empty({N, 4}, f);
    Tensor visible = at::empty({N}, f.dtype(at::kBool));
    Tensor m = means.contiguous(), q = quats.contiguous(), sc = scales.contiguous(), op = opac.contiguous();
    AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "splatzoo_project_cpu", [&] {
        sz::cpu_project<scalar_t>(camera_args<scalar_t>(KR, Kt, eye, W, H), N, m.data_ptr<scalar_t>(),
                                  q.data_ptr<scalar_t>(), sc.data_ptr<scalar_t>(), op.data_ptr<scalar_t>(),
                                  T.data_ptr<scalar_t>(), center.data_ptr<scalar_t>(), depth.data_ptr<scalar_t>(),
                                  normal.data_ptr<scalar_t>(), boxes.data_ptr<scalar_t>(), visible.data_ptr<bool>(),
                                  at::get_num_threads());
    });
    // front to back by centre depth, ties by index: the reference's order
    Tensor vis = at::nonzero(visible).squeeze(1);
    Tensor order = vis.index_select(0, std::get<1>(at::sort(depth.index_select(0, vis), true, 0, false)));
    auto take = [&](const Tensor& t) { return t.index_select(0, order); };
    std::optional<Tensor> counts;
    if (wave_counts.has_value() && wave_counts->defined()) {
        TORCH_CHECK(wave_counts->dim() == 1 && wave_counts->size(0) == N, "splatzoo render: wave_counts must be [N]");
        counts = take(wave_counts->to(at::kInt));
    }
    Inputs in = check_inputs(take(T), take(center), take(depth), take(normal), take(opac), take(base), take(wv),
                             take(wp), take(wa), take(boxes), W, H, counts);
    std::vector<Tensor> o = forward_cpu(in);
    o.insert(o.end(), {in.T, in.center, in.depth, in.normal, in.opac, in.base, in.wv, in.wp, in.wa, in.boxes,
                       in.wc.defined() ? in.wc : at::empty({0}, f.dtype(at::kInt)), order});
    return o;
}

// render_backward(means, quats, scales, KR, Kt, eye, width, height, saved (render's list from index 0: the N_OUT
//                 outputs and state, then the 12 compact tensors), grads of the 6 outputs, has_counts)
// -> [v_means, v_quats, v_scales, v_opacities, v_base, v_wave_vectors, v_wave_phases, v_wave_amplitudes]
std::vector<Tensor> render_backward(const Tensor& means, const Tensor& quats, const Tensor& scales, const Tensor& KR,
                                    const Tensor& Kt, const Tensor& eye, int64_t W, int64_t H,
                                    std::vector<Tensor> saved, std::vector<Tensor> grads, bool has_counts) {
    check_camera(means, KR, Kt, eye);
    TORCH_CHECK(int(saved.size()) == N_OUT + 12, "splatzoo render_backward: got ", saved.size(), " saved tensors");
    std::vector<Tensor> outs(saved.begin(), saved.begin() + N_OUT);
    const Tensor* c = saved.data() + N_OUT;  // T, center, depth, normal, opac, base, wv, wp, wa, boxes, counts, order
    const Tensor& order = c[11];
    std::optional<Tensor> counts;
    if (has_counts) counts = c[10];
    std::vector<Tensor> v = backward(c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7], c[8], c[9], W, H, outs, grads,
                                     counts);
    const int64_t N = means.size(0);
    auto scatter = [&](const Tensor& t) {
        std::vector<int64_t> shape = t.sizes().vec();
        shape[0] = N;
        return at::zeros(shape, t.options()).index_copy_(0, order, t);
    };
    Tensor v_T = scatter(v[0]), v_center = scatter(v[1]), v_depth = scatter(v[2]), v_normal = scatter(v[3]);
    Tensor v_means = at::empty({N, 3}, means.options()), v_quats = at::empty({N, 4}, means.options());
    Tensor v_scales = at::empty({N, 2}, means.options());
    Tensor m = means.contiguous(), q = quats.contiguous(), sc = scales.contiguous();
    AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "splatzoo_project_backward_cpu", [&] {
        sz::cpu_project_backward<scalar_t>(
            camera_args<scalar_t>(KR, Kt, eye, W, H), N, m.data_ptr<scalar_t>(), q.data_ptr<scalar_t>(),
            sc.data_ptr<scalar_t>(), v_T.data_ptr<scalar_t>(), v_center.data_ptr<scalar_t>(),
            v_depth.data_ptr<scalar_t>(), v_normal.data_ptr<scalar_t>(), v_means.data_ptr<scalar_t>(),
            v_quats.data_ptr<scalar_t>(), v_scales.data_ptr<scalar_t>(), at::get_num_threads());
    });
    return {v_means, v_quats, v_scales, scatter(v[4]), scatter(v[5]), scatter(v[6]), scatter(v[7]), scatter(v[8])};
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
    m.doc() = "splatzoo native tile rasterizer (surfels with per-surfel wave colour)";
    namespace py = pybind11;
    m.def("forward", &forward, "Rasterize depth-sorted visible surfels; returns outputs and saved state", py::arg("T"),
          py::arg("center_px"), py::arg("depth"), py::arg("normal"), py::arg("opacities"), py::arg("base_color"),
          py::arg("wave_vectors"), py::arg("wave_phases"), py::arg("wave_amplitudes"), py::arg("boxes"),
          py::arg("width"), py::arg("height"), py::arg("wave_counts") = py::none());
    m.def("backward", &backward, "Gradients of the per-surfel inputs", py::arg("T"), py::arg("center_px"),
          py::arg("depth"), py::arg("normal"), py::arg("opacities"), py::arg("base_color"), py::arg("wave_vectors"),
          py::arg("wave_phases"), py::arg("wave_amplitudes"), py::arg("boxes"), py::arg("width"), py::arg("height"),
          py::arg("outs"), py::arg("grads"), py::arg("wave_counts") = py::none());
    m.def("render", &render, "Project, cull, sort and rasterize surfels on the CPU in one call", py::arg("means"),
          py::arg("quats"), py::arg("scales"), py::arg("opacities"), py::arg("base_color"), py::arg("wave_vectors"),
          py::arg("wave_phases"), py::arg("wave_amplitudes"), py::arg("KR"), py::arg("Kt"), py::arg("eye"),
          py::arg("width"), py::arg("height"), py::arg("wave_counts") = py::none());
    m.def("render_backward", &render_backward, "Gradients of render's surfel inputs", py::arg("means"),
          py::arg("quats"), py::arg("scales"), py::arg("KR"), py::arg("Kt"), py::arg("eye"), py::arg("width"),
          py::arg("height"), py::arg("saved"), py::arg("grads"), py::arg("has_counts"));
    m.attr("GEOM") = sz::GEOM;
    m.attr("N_OUTPUTS") = int(N_OUT);
    m.attr("NEAR") = sz::NEAR;
    m.attr("FAR") = sz::FAR;
    m.attr("ALPHA_MAX") = sz::ALPHA_MAX;
    m.attr("ALPHA_MIN") = sz::ALPHA_MIN;
    m.attr("T_MIN") = sz::T_MIN;
    m.attr("FILTER_INV_SQ") = sz::FILTER_INV_SQ;
    m.attr("PARALLEL_EPS") = sz::PARALLEL_EPS;
    m.attr("TILE") = sz::TILE;
#ifdef SPLATZOO_WITH_CUDA
    m.attr("WITH_CUDA") = true;
#else
    m.attr("WITH_CUDA") = false;
#endif
}
