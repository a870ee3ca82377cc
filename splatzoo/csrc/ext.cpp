// Torch bindings of the native tile rasterizer: render(...) and render_backward(...), one pipeline on three devices:
// the C++ loops on CPU tensors, the CUDA kernels on CUDA tensors (builds with SPLATZOO_WITH_CUDA), and the same CUDA
// kernels under the host emulation on CPU tensors (emulated=True; tests only). splatzoo/rasterizers/native.py wraps
// them in a torch.autograd.Function. Everything crossing the seam is named: a Settings struct, dicts of tensors.
#include <torch/extension.h>

#include <climits>
#include <map>
#include <optional>
#include <string>

#include "rasterize.h"
#include "surfel_math.h"

#ifdef SPLATZOO_WITH_CUDA
#include <c10/cuda/CUDAStream.h>
#endif

namespace {

using at::Tensor;
using TensorMap = std::map<std::string, Tensor>;

enum class Device { Cpu, Gpu, Emulated };

// A CUDA entry point (rasterize.h) on the GPU, or under the host emulation.
#ifdef SPLATZOO_WITH_CUDA
#define SZ_KERNELS(dev, fn, ...) ((dev) == Device::Gpu ? sz::gpu::fn(__VA_ARGS__) : sz::emu::fn(__VA_ARGS__))
#else
#define SZ_KERNELS(dev, fn, ...) sz::emu::fn(__VA_ARGS__)
#endif

constexpr const char* OUTPUTS[] = {"rgb", "alpha", "depth", "median_depth", "normal", "distortion"};

Device device_of(const Tensor& t, bool emulated) {
    if (t.is_cuda()) {
#ifndef SPLATZOO_WITH_CUDA
        TORCH_CHECK(false, "splatzoo: this build of the native rasterizer has no CUDA support, but the surfels are on ",
                    t.device(), "; use the cuda backend's build or move the surfels to the CPU");
#endif
        TORCH_CHECK(!emulated, "splatzoo: the emulated CUDA kernels run on CPU tensors, got ", t.device());
        return Device::Gpu;
    }
    TORCH_CHECK(t.device().is_cpu(), "splatzoo: unsupported device ", t.device());
    return emulated ? Device::Emulated : Device::Cpu;
}

void* stream_for(Device dev) {
#ifdef SPLATZOO_WITH_CUDA
    if (dev == Device::Gpu) return c10::cuda::getCurrentCUDAStream().stream();
#endif
    return nullptr;
}

const Tensor& need(const TensorMap& m, const std::string& key) {
    auto it = m.find(key);
    TORCH_CHECK(it != m.end(), "splatzoo render_backward: the saved state has no ", key,
                " (state from another splatzoo version?)");
    return it->second;
}

template <class S>
sz::CameraArgs<S> camera_args(const Tensor& KR, const Tensor& Kt, const Tensor& eye, int64_t W, int64_t H) {
    TORCH_CHECK(KR.numel() == 9 && Kt.numel() == 3 && eye.numel() == 3,
                "splatzoo render: camera tensors KR [3,3], Kt [3], eye [3] expected");
    auto host = [](const Tensor& t) { return t.detach().to(at::kCPU, c10::CppTypeToScalarType<S>::value).contiguous(); };
    Tensor kr = host(KR), kt = host(Kt), e = host(eye);
    sz::CameraArgs<S> c;
    for (int i = 0; i < 9; ++i) c.KR[i] = kr.data_ptr<S>()[i];
    for (int i = 0; i < 3; ++i) {
        c.Kt[i] = kt.data_ptr<S>()[i];
        c.eye[i] = e.data_ptr<S>()[i];
    }
    c.W = int(W);
    c.H = int(H);
    return c;
}

// The batch's sizes, the wave count K and the texels a side T, from the saved per-pair fields by the table: each the
// size of the first field with that dimension (0 if none has it).
void batch_sizes(const TensorMap& c, int64_t& K, int64_t& TS) {
    K = -1;
    TS = -1;
    for (const sz::SurfelFieldInfo& info : sz::SURFEL_FIELD_INFO) {
        if (info.role == sz::Role::geometry) continue;
        for (int d = 0; d < info.rank; ++d) {
            if (info.dims[d] == sz::SZ_K && K < 0) K = need(c, info.name).size(d + 1);
            if (info.dims[d] == sz::SZ_T && TS < 0) TS = need(c, info.name).size(d + 1);
        }
    }
    K = K < 0 ? 0 : K;
    TS = TS < 0 ? 0 : TS;
}

// The surfels, their projection and the visible ones' depth order, as the tile loops read them.
template <class S>
sz::SurfelArgs<S> surfel_args(const sz::Settings& st, const TensorMap& c, int64_t W, int64_t H) {
    const Tensor& order = need(c, "order");
    auto wc = c.find("wave_counts");
    auto prepared = c.find("appearance_prepared");
    int64_t K = 0, TS = 0;
    batch_sizes(c, K, TS);
    sz::SurfelArgs<S> a{};
    a.st = st;
    a.N = int(need(c, "T").size(0));
    a.M = int(order.size(0));
    a.K = int(K);
    a.TS = int(TS);
    a.prepared = prepared != c.end() ? prepared->second.data_ptr<S>() : nullptr;
    a.prepared_width = prepared != c.end() ? int(prepared->second.size(1)) : 0;
    a.W = int(W);
    a.H = int(H);
    a.order = order.data_ptr<int>();
    a.T = need(c, "T").data_ptr<S>();
    a.center = need(c, "centers").data_ptr<S>();
    a.depth = need(c, "center_depths").data_ptr<S>();
    a.normal = need(c, "normals").data_ptr<S>();
    a.boxes = need(c, "boxes").data_ptr<S>();
#define SZ_SET_FIELD(name) a.name = need(c, #name).data_ptr<S>();
    SZ_PAIR_FIELDS(SZ_SET_FIELD)
#undef SZ_SET_FIELD
    a.wcount = wc != c.end() ? wc->second.data_ptr<int>() : nullptr;
    return a;
}

// GradArgs' v_<name> of every per-pair field, from the gradient buffers by name.
template <class S>
void set_field_gradients(sz::GradArgs<S>& g, TensorMap& v) {
#define SZ_SET_GRADIENT(name) g.v_##name = v.at(#name).data_ptr<S>();
    SZ_PAIR_FIELDS(SZ_SET_GRADIENT)
#undef SZ_SET_GRADIENT
}

// The frame: binning, per-pixel saved state and, given `out` (the forward), the outputs to write. The backward
// passes none: it reads the saved state and the depth output only. image_only: `out` holds rgb and alpha and there
// is no per-pixel state (those pointers stay null).
template <class S>
sz::FrameArgs<S> frame_args(const TensorMap& st, const TensorMap* out, bool image_only = false) {
    auto p = [&](const TensorMap& m, const char* k) { return need(m, k).data_ptr<S>(); };
    auto o = [&](const char* k) { return out ? p(*out, k) : nullptr; };
    auto full = [&](const TensorMap& m, const char* k) { return image_only ? nullptr : p(m, k); };
    auto i = [&](const char* k) { return need(st, k).data_ptr<int>(); };
    auto saved = [&](const char* k) { return image_only ? nullptr : i(k); };
    return {p(st, "geom"), i("bounds"), i("tile_start"), i("tile_list"),
            o("rgb"), o("alpha"), out ? full(*out, "depth") : p(st, "depth"), out ? full(*out, "median_depth") : nullptr,
            out ? full(*out, "normal") : nullptr, out ? full(*out, "distortion") : nullptr, full(st, "T_final"),
            full(st, "totals"), saved("last"), saved("median_index"), image_only};
}

// The per-surfel fields in table order (surfel_fields.h), checked against the table: one dtype and device, shape
// [N, trailing dims] with K the wave count of the first field that has one and TS the texture size of the first
// that has one. Returns them by name, contiguous.
TensorMap check_surfels(const std::vector<Tensor>& fields, int64_t& N, int64_t& K, int64_t& TS) {
    TORCH_CHECK(int(fields.size()) == sz::NUM_SURFEL_FIELDS, "splatzoo render: ", sz::NUM_SURFEL_FIELDS,
                " surfel fields expected (the Surfels field table), got ", fields.size(),
                " (a build from another splatzoo version?)");
    const Tensor& first = fields[0];
    TORCH_CHECK(first.scalar_type() == at::kFloat || first.scalar_type() == at::kDouble,
                "splatzoo render: float32 or float64 surfels expected, got ", first.scalar_type());
    N = first.dim() >= 1 ? first.size(0) : -1;
    TORCH_CHECK(N >= 0 && N < INT_MAX, "splatzoo render: bad number of surfels ", first.sizes());
    K = -1;
    TS = -1;
    TensorMap out;
    for (int i = 0; i < sz::NUM_SURFEL_FIELDS; ++i) {
        const sz::SurfelFieldInfo& info = sz::SURFEL_FIELD_INFO[i];
        const Tensor& t = fields[i];
        std::vector<int64_t> shape = {N};
        for (int d = 0; d < info.rank; ++d) {
            if (info.dims[d] == sz::SZ_K && K < 0 && t.dim() == info.rank + 1) K = t.size(d + 1);
            if (info.dims[d] == sz::SZ_T && TS < 0 && t.dim() == info.rank + 1) TS = t.size(d + 1);
            shape.push_back(info.dims[d] == sz::SZ_K ? K : info.dims[d] == sz::SZ_T ? TS : info.dims[d]);
        }
        TORCH_CHECK(t.sizes().vec() == shape, "splatzoo render: ", info.name, " must have shape ",
                    at::IntArrayRef(shape), ", got ", t.sizes());
        TORCH_CHECK(t.scalar_type() == first.scalar_type() && t.device() == first.device(), "splatzoo render: ",
                    info.name, " must be ", first.scalar_type(), " on ", first.device(), " like ",
                    sz::SURFEL_FIELD_INFO[0].name);
        out[info.name] = t.contiguous();
    }
    if (K < 0) K = 0;
    if (TS < 0) TS = 0;
    TORCH_CHECK(TS <= 64, "splatzoo render: textures of at most 64x64 texels, got ", TS, "x", TS);
    return out;
}

// render(settings, fields, wave_counts, KR, Kt, eye, width, height, emulated, image_only) -> (outputs, state), two
// dicts of tensors; fields: the per-surfel tensors in the order of the field table (surfel_fields.h). image_only:
// outputs rgb and alpha only, and no state (a render to look at, not to differentiate).
// outputs: rgb [H,W,3], alpha, depth, median_depth [H,W], normal [H,W,3], distortion [H,W] (before the background);
// state: what render_backward needs (the projection, the depth order of the visible surfels, the binning, the
// per-pixel totals), every per-surfel tensor in input order.
std::pair<TensorMap, TensorMap> render(const sz::Settings& st, const std::vector<Tensor>& fields,
                                       const std::optional<Tensor>& wave_counts, const Tensor& KR, const Tensor& Kt,
                                       const Tensor& eye, int64_t W, int64_t H, bool emulated, bool image_only) {
    int64_t N = 0, K = 0, TS = 0;
    const TensorMap surfels = check_surfels(fields, N, K, TS);
    const Tensor& means = surfels.at("means");
    TORCH_CHECK(W >= 1 && H >= 1 && W <= (1 << 20) && H <= (1 << 20) && W * H <= int64_t(INT_MAX),
                "splatzoo render: bad image size ", W, "x", H, " (at most 2^20 a side and 2^31 - 1 pixels)");
    const Device dev = device_of(means, emulated);
    const at::OptionalDeviceGuard guard(at::device_of(means));
    void* stream = stream_for(dev);
    const int threads = at::get_num_threads();
    auto f = means.options();
    auto i32 = f.dtype(at::kInt);
    const Tensor &m = means, &q = surfels.at("quats"), &sc = surfels.at("scales"), &op = surfels.at("opacities"),
                 &fo = surfels.at("falloff");

    // 1. project every surfel: T, centre, depth, normal, exact screen box, visibility
    Tensor T = at::empty({N, 3, 3}, f), center = at::empty({N, 2}, f), depth = at::empty({N}, f);
    Tensor normal = at::empty({N, 3}, f), boxes = at::empty({N, 4}, f), visible = at::empty({N}, f.dtype(at::kBool));
    AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "splatzoo_project", [&] {
        sz::ProjectArgs<scalar_t> a{st, camera_args<scalar_t>(KR, Kt, eye, W, H), N, m.data_ptr<scalar_t>(),
                                    q.data_ptr<scalar_t>(), sc.data_ptr<scalar_t>(), op.data_ptr<scalar_t>(),
                                    fo.data_ptr<scalar_t>(), T.data_ptr<scalar_t>(), center.data_ptr<scalar_t>(), depth.data_ptr<scalar_t>(),
                                    normal.data_ptr<scalar_t>(), boxes.data_ptr<scalar_t>(), visible.data_ptr<bool>()};
        if (dev == Device::Cpu)
            sz::cpu_project<scalar_t>(a, threads);
        else
            SZ_KERNELS(dev, project<scalar_t>, a, stream);
    });

    // 2. the visible ones, front to back by centre depth, ties by index (the reference's order); the per-surfel
    // arrays stay in input order
    Tensor vis = at::nonzero(visible).squeeze(1);
    Tensor order = vis.index_select(0, std::get<1>(at::sort(depth.index_select(0, vis), true, 0, false)));
    const int64_t M = order.size(0);
    TensorMap state = {{"order", order.to(at::kInt)}, {"T", T}, {"centers", center}, {"center_depths", depth},
                       {"normals", normal}, {"boxes", boxes}};
    for (const sz::SurfelFieldInfo& info : sz::SURFEL_FIELD_INFO)
        if (info.role != sz::Role::geometry) state[info.name] = surfels.at(info.name);
    if (wave_counts.has_value() && wave_counts->defined()) {
        const Tensor& wc = *wave_counts;
        TORCH_CHECK(wc.dim() == 1 && wc.size(0) == N && !wc.is_floating_point() && wc.device() == means.device(),
                    "splatzoo render: wave_counts must be an integer tensor [", N, "] on ", means.device(), ", got ",
                    wc.scalar_type(), " ", wc.sizes(), " on ", wc.device());
        if (N > 0) {  // an out-of-range count would read past the surfel's row (one sync for both bounds)
            const Tensor range = at::stack({wc.min(), wc.max()}).to(at::kCPU, at::kLong);
            TORCH_CHECK(range[0].item<int64_t>() >= 0 && range[1].item<int64_t>() <= K,
                        "splatzoo render: wave_counts must lie in [0, K=", K, "]");
        }
        state["wave_counts"] = wc.to(at::kInt).contiguous();
    }

    // 3. pixel geometry, then (tile, surfel) pairs binned tile-major in depth order
    const int nt = sz::tiles_x(int(W)) * sz::tiles_y(int(H));
    state["geom"] = at::empty({N, sz::GEOM}, f);
    state["bounds"] = at::empty({N, 4}, i32);
    state["tile_start"] = at::empty({nt + 1}, i32);
    // the appearance's per-surfel set-up (anti-aliased: the prefiltered textures), by the prepare step
    const int prepared = sz::Appearance<float>::prepared_width(int(K), int(TS), st.pixel_filter > 0);
    if (prepared > 0) state["appearance_prepared"] = at::empty({N, prepared}, f);
    AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "splatzoo_bin", [&] {
        const auto s = surfel_args<scalar_t>(st, state, W, H);
        scalar_t* geom = state["geom"].data_ptr<scalar_t>();
        int* bounds = state["bounds"].data_ptr<int>();
        int64_t P = 0;
        if (dev == Device::Cpu) {  // a counting sort that also records each pair's position for the backward
            state["surfel_off"] = at::empty({M + 1}, f.dtype(at::kLong));
            P = sz::cpu_prepare<scalar_t>(s, geom, bounds, state["surfel_off"].data_ptr<int64_t>(), threads);
            TORCH_CHECK(P < INT_MAX, "splatzoo render: ", P, " (tile, surfel) pairs exceed 2^31; render at a lower "
                        "resolution or with fewer or smaller surfels");
            state["tile_list"] = at::empty({P}, i32);
            state["pair_pos"] = at::empty({P}, i32);
            sz::cpu_bin(int(M), int(W), int(H), s.order, bounds, state["surfel_off"].data_ptr<int64_t>(),
                        state["tile_start"].data_ptr<int>(), state["tile_list"].data_ptr<int>(),
                        state["pair_pos"].data_ptr<int>());
        } else {  // one key per pair (tile << 32 | depth rank), sorted
            Tensor count = at::empty({M}, i32);
            SZ_KERNELS(dev, prepare<scalar_t>, s, geom, bounds, count.data_ptr<int>(), stream);
            Tensor pair_end = at::cumsum(count, 0, at::kLong);
            P = M > 0 ? pair_end[M - 1].item<int64_t>() : 0;
            TORCH_CHECK(P < INT_MAX, "splatzoo render: ", P, " (tile, surfel) pairs exceed 2^31; render at a lower "
                        "resolution or with fewer or smaller surfels");
            Tensor keys = at::empty({P}, f.dtype(at::kLong));
            SZ_KERNELS(dev, emit_pairs, int(M), int(W), s.order, bounds, pair_end.data_ptr<int64_t>(),
                       keys.data_ptr<int64_t>(), stream);
            keys = std::get<0>(at::sort(keys));
            state["tile_list"] = at::empty({P}, i32);
            if (P == 0) state["tile_start"].zero_();
            SZ_KERNELS(dev, tile_starts, P, nt, s.order, keys.data_ptr<int64_t>(), state["tile_list"].data_ptr<int>(),
                       state["tile_start"].data_ptr<int>(), stream);
        }
    });

    // 4. the tile loop; a render to look at (image_only) writes rgb and alpha only and keeps no per-pixel state
    TensorMap out = {{"rgb", at::empty({H, W, 3}, f)}, {"alpha", at::empty({H, W}, f)}};
    if (!image_only) {
        out["depth"] = at::empty({H, W}, f);
        out["median_depth"] = at::empty({H, W}, f);
        out["normal"] = at::empty({H, W, 3}, f);
        out["distortion"] = at::empty({H, W}, f);
        state["T_final"] = at::empty({H, W}, f);
        state["totals"] = at::empty({H, W, 3}, f);
        state["last"] = at::empty({H, W}, i32);
        state["median_index"] = at::empty({H, W}, i32);
    }
    AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "splatzoo_forward", [&] {
        const auto s = surfel_args<scalar_t>(st, state, W, H);
        const auto fr = frame_args<scalar_t>(state, &out, image_only);
        if (dev == Device::Cpu)
            sz::cpu_forward<scalar_t>(s, fr, threads);
        else
            SZ_KERNELS(dev, forward<scalar_t>, s, fr, stream);
    });
    if (image_only) return {out, TensorMap{}};
    state["depth"] = out["depth"];  // the backward divides by the accumulated alpha through it
    return {out, state};
}

// render_backward(settings, means, quats, scales, KR, Kt, eye, width, height, state, cotangents, emulated)
// -> dict of v_ gradients by surfel field, every field of the table (missing cotangents count as zero; waves beyond
//    a surfel's count get zero).
TensorMap render_backward(const sz::Settings& st, const Tensor& means, const Tensor& quats, const Tensor& scales,
                          const Tensor& KR, const Tensor& Kt, const Tensor& eye, int64_t W, int64_t H,
                          const TensorMap& state, const TensorMap& cotangents, bool emulated) {
    const Device dev = device_of(means, emulated);
    const at::OptionalDeviceGuard guard(at::device_of(means));
    void* stream = stream_for(dev);
    const int threads = at::get_num_threads();
    auto f = means.options();
    const int64_t N = means.size(0), M = need(state, "order").size(0);
    TensorMap v_out;  // cotangents of the six outputs, contiguous, zeros where not given
    for (const char* name : OUTPUTS) {
        std::vector<int64_t> shape = {H, W};
        if (name == std::string("rgb") || name == std::string("normal")) shape.push_back(3);
        auto it = cotangents.find(name);
        v_out[name] = it != cotangents.end() && it->second.defined()
                          ? it->second.to(means.device(), means.scalar_type()).contiguous()
                          : at::zeros(shape, f);
        TORCH_CHECK(v_out[name].sizes().vec() == shape, "splatzoo render_backward: cotangent of ", name,
                    " must have shape ", at::IntArrayRef(shape), ", got ", v_out[name].sizes());
    }
    // gradients of the per-surfel tensors, in input order; invisible surfels keep zero. The per-pair fields' are
    // shaped like the saved fields themselves
    TensorMap v_c = {{"T", at::zeros({N, 3, 3}, f)}, {"centers", at::zeros({N, 2}, f)},
                     {"center_depths", at::zeros({N}, f)}, {"normals", at::zeros({N, 3}, f)}};
    for (const sz::SurfelFieldInfo& info : sz::SURFEL_FIELD_INFO)
        if (info.role != sz::Role::geometry) v_c[info.name] = at::zeros_like(need(state, info.name));
    int64_t K = 0, TS = 0;
    batch_sizes(state, K, TS);
    const int GW = sz::grad_width(int(K), int(TS));
    if (M > 0) {
        AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "splatzoo_backward", [&] {
            using S = scalar_t;
            const auto s = surfel_args<S>(st, state, W, H);
            const auto fr = frame_args<S>(state, nullptr);
            sz::GradArgs<S> g{};
            g.v_rgb = v_out["rgb"].data_ptr<S>();
            g.v_alpha = v_out["alpha"].data_ptr<S>();
            g.v_depth = v_out["depth"].data_ptr<S>();
            g.v_median = v_out["median_depth"].data_ptr<S>();
            g.v_normal = v_out["normal"].data_ptr<S>();
            g.v_dist = v_out["distortion"].data_ptr<S>();
            g.v_T = v_c["T"].data_ptr<S>();
            g.v_center = v_c["centers"].data_ptr<S>();
            g.v_depth_c = v_c["center_depths"].data_ptr<S>();
            g.v_normal_c = v_c["normals"].data_ptr<S>();
            set_field_gradients(g, v_c);
            if (dev == Device::Cpu) {
                Tensor partials = at::empty({need(state, "tile_list").size(0), GW}, f);
                sz::cpu_backward<S>(s, fr, g, need(state, "surfel_off").data_ptr<int64_t>(),
                                    need(state, "pair_pos").data_ptr<int>(), partials.data_ptr<S>(), threads);
            } else {
                Tensor rows = at::zeros({N, GW}, f);
                SZ_KERNELS(dev, backward<S>, s, fr, g, rows.data_ptr<S>(), stream);
            }
        });
    }
    // then through the projection
    const Tensor &v_T = v_c["T"], &v_center = v_c["centers"], &v_depth = v_c["center_depths"];
    const Tensor& v_normal = v_c["normals"];
    Tensor v_means = at::empty({N, 3}, f), v_quats = at::empty({N, 4}, f), v_scales = at::empty({N, 2}, f);
    Tensor m = means.contiguous(), q = quats.contiguous(), sc = scales.contiguous();
    AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "splatzoo_project_backward", [&] {
        using S = scalar_t;
        sz::ProjectGradArgs<S> a{st, camera_args<S>(KR, Kt, eye, W, H), N, m.data_ptr<S>(), q.data_ptr<S>(),
                                 sc.data_ptr<S>(), v_T.data_ptr<S>(), v_center.data_ptr<S>(), v_depth.data_ptr<S>(),
                                 v_normal.data_ptr<S>(), v_means.data_ptr<S>(), v_quats.data_ptr<S>(),
                                 v_scales.data_ptr<S>()};
        if (dev == Device::Cpu)
            sz::cpu_project_backward<S>(a, threads);
        else
            SZ_KERNELS(dev, project_backward<S>, a, stream);
    });
    TensorMap v = {{"means", v_means}, {"quats", v_quats}, {"scales", v_scales}};
    for (const sz::SurfelFieldInfo& info : sz::SURFEL_FIELD_INFO)
        if (info.role != sz::Role::geometry) v[info.name] = v_c[info.name];
    return v;
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
    m.doc() = "splatzoo native tile rasterizer (surfels with per-surfel wave colour)";
    namespace py = pybind11;
    // module_local: the CPU and the CUDA builds may be loaded in one process, each with its own Settings type
    py::class_<sz::Settings>(m, "Settings", py::module_local(), "The rasterizer's numeric settings (from RasterSettings)")
        .def(py::init<>())
        .def_readwrite("near", &sz::Settings::near)
        .def_readwrite("far", &sz::Settings::far)
        .def_readwrite("alpha_max", &sz::Settings::alpha_max)
        .def_readwrite("alpha_min", &sz::Settings::alpha_min)
        .def_readwrite("t_min", &sz::Settings::t_min)
        .def_readwrite("filter_inv_sq", &sz::Settings::filter_inv_sq)
        .def_readwrite("parallel_eps", &sz::Settings::parallel_eps)
        .def_readwrite("pixel_filter", &sz::Settings::pixel_filter);
    // the fields above, so the Python side can check it sets every one
    m.attr("SETTINGS_FIELDS") = py::make_tuple("near", "far", "alpha_max", "alpha_min", "t_min", "filter_inv_sq",
                                               "parallel_eps", "pixel_filter");
    m.def("render", &render, "Project, cull, sort, bin and rasterize surfels; returns (outputs, state)",
          py::arg("settings"), py::arg("fields"), py::arg("wave_counts"), py::arg("KR"), py::arg("Kt"), py::arg("eye"),
          py::arg("width"), py::arg("height"), py::arg("emulated") = false, py::arg("image_only") = false);
    // the field table this build was compiled with (surfel_fields.h), in the order render() takes them
    py::list names;
    for (const sz::SurfelFieldInfo& info : sz::SURFEL_FIELD_INFO) names.append(info.name);
    m.attr("SURFEL_FIELDS") = py::tuple(names);
    m.def("render_backward", &render_backward, "Gradients of render's surfel inputs (dict by field name)",
          py::arg("settings"), py::arg("means"), py::arg("quats"), py::arg("scales"), py::arg("KR"), py::arg("Kt"),
          py::arg("eye"), py::arg("width"), py::arg("height"), py::arg("state"), py::arg("cotangents"),
          py::arg("emulated") = false);
    m.attr("GEOM") = sz::GEOM;
    m.attr("TILE") = sz::TILE;
#ifdef SPLATZOO_WITH_CUDA
    m.attr("WITH_CUDA") = true;
#else
    m.attr("WITH_CUDA") = false;
#endif
}
