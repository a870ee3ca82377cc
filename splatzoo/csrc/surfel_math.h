// Per-(surfel, pixel) maths of the splatzoo tile rasterizers, written once for the C++ and the CUDA tile loops.
//
// It reproduces splatzoo/rasterizers/reference.py (_shade_rect and the kinds' twins) operation for operation, plus the
// hand-written derivatives. The tile loops (rasterize_cpu.cpp, rasterize_cuda.cu) own binning and traversal only.
//
// Gradients of one (surfel, pixel) pair are accumulated through a functor `acc(slot, value)` into the slots below
// (a per-surfel row of grad_width(K, T) scalars); finalize_grads() turns a summed row into gradients of the op inputs.
//
// What a surfel looks like is its appearance: a composition of kinds (the wave bank, the texture), one section each
// below, with the kernel falloff (Gaussian, Beta) a declared part of the same contract. The tile loops ask the
// composition (Appearance) and the falloff dispatch (with_falloff); they name no kind.
#pragma once

#include <cmath>
#include <cstdint>
#include <cstring>

#include "surfel_fields.h"

#ifdef __CUDACC__
#define SZ_HD __host__ __device__ __forceinline__
#define SZ_INLINE_LAMBDA
#else
#define SZ_HD inline __attribute__((always_inline))
// A lambda that stands in for inlined code (a body handed to with_falloff): GCC may keep a generic lambda out of line,
// and contracts multiply-adds into FMAs only within a function, so the pair's maths would round otherwise.
#define SZ_INLINE_LAMBDA __attribute__((always_inline))
#endif

namespace sz {

// The rasterizer's numeric settings. Their values have one source, splatzoo.rasterizers.common.RasterSettings,
// whose fields the bindings copy into this struct, by name, on every call.
struct Settings {
    double near;           // hits closer than this camera depth are culled
    double far;            // far plane of the distortion term's NDC depth
    double alpha_max;      // alpha clamp
    double alpha_min;      // contributions with a smaller alpha are skipped
    double t_min;          // stop before a contribution that would bring transmittance below this
    double filter_inv_sq;  // screen-space low-pass filter: rho2d = filter_inv_sq |pixel - centre|^2
    double parallel_eps;   // a ray with |c_z| <= parallel_eps max(|c_x|, |c_y|) misses the surfel's plane
    double pixel_filter;   // variance (px^2) of the anti-aliasing pixel footprint; 0: off (the screen filter instead)
};

// Compile time, not a setting: a CUDA block is one tile. RasterSettings.tile is checked against it.
constexpr int TILE = 16;
constexpr int TILE_PIXELS = TILE * TILE;

// Per-surfel geometry prepared once per render (prepare_geom): GEOM scalars, in this order. (The CUDA kernels
// stage BLOCK of them in shared memory, at most 48 KB a block: 21 doubles each is the most that fits.)
constexpr int GEOM = 20;
template <class S>
struct Geom {
    S A[3], B[3], C[3];  // c(x, y) = (x - cx) A + (y - cy) B + C   (the cross product h_x x h_y, expanded)
    S cx, cy, zc;        // projected centre (pixels) and camera depth of the centre
    S m3[3];             // third row of T: hit depth z = m3 . (u, v, 1)
    S o;                 // opacity
    S blur[3];           // anti-aliased: the kinds' blur I - (I + S)^-1, S the footprint at the centre (else 0)
    S s;                 // falloff exponent: 0 the Gaussian, > 0 the Beta kernel (with_falloff below)
};

// Gradient slots of one surfel row: the pair's geometry and opacity, then the appearance's blocks: every kind's dense
// block in table order, then every kind's scatter block (see the appearance section), [G_APPEARANCE, grad_width).
enum : int {
    G_C = 0,        // sum over pixels of dL/dc            (3)
    G_CX = 3,       // sum of (x - cx) dL/dc               (3)
    G_CY = 6,       // sum of (y - cy) dL/dc               (3)
    G_M3 = 9,       // dL/dm3 through the hit depth        (3)
    G_ZC = 12,      // dL/d centre depth (filter wins)     (1)
    G_CENTER = 13,  // dL/d centre_px through the filter   (2)
    G_O = 15,       // dL/d opacity                        (1)
    G_NORMAL = 16,  // dL/d surfel normal                  (3)
    G_A = 19,       // dL/dA through the footprint's Jacobian (3; anti-aliased only)
    G_B = 22,       // dL/dB through the footprint's Jacobian (3; anti-aliased only)
    G_S = 25,       // dL/d falloff exponent                (1)
    G_APPEARANCE = 26,  // the appearance's blocks start here
};

// ---- small branch-free helpers (they must vectorise inside `omp simd` loops) ------------------------------------
template <class S> SZ_HD S sabs(S x) { return x < S(0) ? -x : x; }
template <class S> SZ_HD S smax(S a, S b) { return a > b ? a : b; }
template <class S> SZ_HD S smin(S a, S b) { return a < b ? a : b; }

// Bit casts between float and 32-bit integers, on either side.
SZ_HD uint32_t float_bits(float x) {
#ifdef __CUDA_ARCH__
    return __float_as_uint(x);
#else
    uint32_t b;
    std::memcpy(&b, &x, sizeof(b));
    return b;
#endif
}
SZ_HD float bits_float(uint32_t b) {
#ifdef __CUDA_ARCH__
    return __uint_as_float(b);
#else
    float x;
    std::memcpy(&x, &b, sizeof(x));
    return x;
#endif
}

// Round to nearest for |x| < 2^22 without a libm call (GCC does not vectorise std::floor under the default
// -ftrapping-math): adding and subtracting 1.5 * 2^23 drops the fraction bits. Never build this header
// with -ffast-math, which may fold the two additions away.
SZ_HD float round_magic(float x) {
    return (x + 12582912.0f) - 12582912.0f;
}

// exp for float on the host: Cephes polynomial with an explicit 2^n, so GCC can vectorise it (libm's expf is a call).
// About 1 ulp on [-87, 88]; clamped below so 2^n stays a normal number.
SZ_HD float exp_poly(float x) {
    // Bounds that depend on x (0 * x is not folded without -ffast-math): with constant bounds GCC's PRE turns the
    // clamp into a branch around the whole polynomial and the loop no longer vectorises.
    const float zero = 0.0f * x;
    x = smin(smax(x, -87.0f + zero), 88.0f + zero);
    float n = round_magic(x * 1.44269504088896341f);
    float r = x - n * 0.693359375f - n * -2.12194440e-4f;
    float p = 1.9875691500e-4f;
    p = p * r + 1.3981999507e-3f;
    p = p * r + 8.3334519073e-3f;
    p = p * r + 4.1665795894e-2f;
    p = p * r + 1.6666665459e-1f;
    p = p * r + 5.0000001201e-1f;
    float y = p * r * r + r + 1.0f;
    const float scale = bits_float(static_cast<uint32_t>((static_cast<int32_t>(n) + 127) << 23));
    return y * scale;
}

// ln(1 - x) for float on the host, 0 <= x < 1, without a libm call (so the Beta kernel's pixel loops vectorise, as
// exp_poly's): a series for x < 1/16, else w = 1 - x split as 2^e m, m in [sqrt(1/2), sqrt(2)), and
// ln m = 2 atanh(t), t = (m - 1)/(m + 1), |t| <= 0.172. About 1e-7 relative, plus w's own rounding beyond 1/16.
SZ_HD float log1m_poly(float x) {
    const float series = -x * (1.0f + x * (0.5f + x * (0.333333343f + x * (0.25f + x * (0.2f + x * (0.166666672f +
                                                                                              x * 0.142857149f))))));
    float w = 1.0f - x;
    w = w > 1.17549435e-38f ? w : 1.17549435e-38f;  // normal: the exponent field is the exponent
    const uint32_t b = float_bits(w);
    float e = float(static_cast<int32_t>(b >> 23) - 126);
    float m = bits_float((b & 0x007fffffu) | 0x3f000000u);  // [1/2, 1)
    const bool low = m < 0.707106781f;
    m = low ? m + m : m;
    e = low ? e - 1.0f : e;
    const float t = (m - 1.0f) / (m + 1.0f), t2 = t * t;
    const float lm = 2.0f * t * (1.0f + t2 * (0.333333343f + t2 * (0.2f + t2 * (0.142857149f + t2 * (0.111111112f +
                                                                                               t2 * 0.0909090936f)))));
    const float logw = e * 0.693359375f + (e * -2.12194440e-4f + lm);
    return x < 0.0625f ? series : logw;
}

// sin and cos for float: Cody-Waite reduction by pi/2 and Cephes polynomials (about 1e-7 absolute for |x| < 1e4,
// finite and within [-1, 1] beyond; |x| is clamped at 1e6). On the host, scalar libm sincosf costs several times
// more per call; on a GPU, CUDA's sincosf keeps a slow path for huge arguments that needs a stack frame.
SZ_HD void sincos_poly(float x, float& s, float& c) {
    const float zero = 0.0f * x;  // see exp_poly
    x = smin(smax(x, -1e6f + zero), 1e6f + zero);
    float j = round_magic(x * 0.636619772367581343f);
    float r = ((x - j * 1.5703125f) - j * 4.837512969970703125e-4f) - j * 7.54978995489188216e-8f;
    float r2 = r * r;
    float ps = ((-1.9515295891e-4f * r2 + 8.3321608736e-3f) * r2 - 1.6666654611e-1f) * r2 * r + r;
    float pc = ((2.443315711809948e-5f * r2 - 1.388731625493765e-3f) * r2 + 4.166664568298827e-2f) * r2 * r2
               - 0.5f * r2 + 1.0f;
    // Quadrant q: swap sin and cos for odd q, flip signs by q. Done on the bits: as ?: selects, scalar code (a wave
    // count other than the vector width) compiled to branches on the phase, mispredicted half the time.
    const uint32_t q = static_cast<uint32_t>(static_cast<int32_t>(j));
    const uint32_t swap = 0u - (q & 1u);  // all ones for odd q
    const uint32_t bs = float_bits(ps), bc = float_bits(pc);
    uint32_t sv = (bs & ~swap) | (bc & swap);
    uint32_t cv = (bc & ~swap) | (bs & swap);
    sv ^= (q & 2u) << 30;           // sin < 0 in quadrants 2, 3
    cv ^= ((q + 1u) & 2u) << 30;    // cos < 0 in quadrants 1, 2
    s = bits_float(sv);
    c = bits_float(cv);
}

SZ_HD float sz_exp(float x) {
#ifdef __CUDA_ARCH__
    return expf(x);
#else
    return exp_poly(x);
#endif
}
SZ_HD double sz_exp(double x) { return exp(x); }

SZ_HD void sz_sincos(float x, float& s, float& c) { sincos_poly(x, s, c); }
SZ_HD void sz_sincos(double x, double& s, double& c) {
    s = sin(x);
    c = cos(x);
}

// ln(1 - x), 0 <= x < 1 (the Beta kernel's log)
SZ_HD float sz_log1m(float x) {
#ifdef __CUDA_ARCH__
    return log1pf(-x);
#else
    return log1m_poly(x);
#endif
}
SZ_HD double sz_log1m(double x) { return log1p(-x); }

// ---- the kernel falloff's support (the falloff itself is below, after rmul) ------------------------------------
// The support of opacity o: rho <= 2 ln(o / alpha_min) for the Gaussian, (2/s)(1 - (alpha_min / o)^s) for the Beta
// kernel (contributions below alpha_min are skipped). log_o = ln(o / alpha_min) > 0.
SZ_HD double support_rho(double log_o, double s) {
    return s > 0.0 ? -2.0 * expm1(-s * log_o) / s : 2.0 * log_o;
}

// ---- projection: the camera-dependent set-up of common.project and common.screen_boxes ------------------------
// KR = K R_cam (row-major), Kt = K t, eye = camera centre in world coordinates; W, H the image size.
template <class S>
struct CameraArgs {
    S KR[9], Kt[3], eye[3];
    int W, H;
};

// NaN-propagating min/max, as torch.minimum / torch.maximum (smin/smax drop a NaN operand).
template <class S> SZ_HD S nan_min(S a, S b) { return (a != a || b != b) ? a + b : (a < b ? a : b); }
template <class S> SZ_HD S nan_max(S a, S b) { return (a != a || b != b) ? a + b : (a > b ? a : b); }

// Rotation (row-major) of the quaternion (w, x, y, z) divided by max(|q|, 1e-12), as geometry.quat_to_rotmat.
template <class S>
SZ_HD void quat_rotmat(const S* q, S R[9], S qn[4], S& norm) {
    norm = sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    const S nc = smax(norm, S(1e-12));
    for (int i = 0; i < 4; ++i) qn[i] = q[i] / nc;
    const S w = qn[0], x = qn[1], y = qn[2], z = qn[3];
    R[0] = S(1) - S(2) * (y * y + z * z); R[1] = S(2) * (x * y - w * z);         R[2] = S(2) * (x * z + w * y);
    R[3] = S(2) * (x * y + w * z);         R[4] = S(1) - S(2) * (x * x + z * z); R[5] = S(2) * (y * z - w * x);
    R[6] = S(2) * (x * z - w * y);         R[7] = S(2) * (y * z + w * x);         R[8] = S(1) - S(2) * (x * x + y * y);
}

// ---- anti-aliasing footprint (common.centre_footprint, common.FOOTPRINT_PAD, common.LINEAR_LIMIT) ------------
constexpr double FOOTPRINT_PAD = 0.05;     // culling boxes grow by this fraction of their size ...
constexpr double FOOTPRINT_PAD_PX = 1.0;   // ... and this many pixels, times the tilt (they bound the support)
constexpr double LINEAR_LIMIT = 0.2;       // pairs whose footprint sigma exceeds this fraction of the distance to
                                           // the plane's vanishing line are culled

// The pixel footprint at the projected centre (common.centre_footprint), in double. There c = (0, 0, cz): J =
// d(u, v)/d(pixel) = [[A0, B0], [A1, B1]] / cz with A = m2 x m3, B = m3 x m1, cz = C2 + cx A2 + cy B2; the
// footprint's covariance in the surfel's frame is S = pixel_filter J J^T, and tilt (0..1) says how much J changes
// over the surfel (cz is affine in the pixel, gradient (A2, B2)). The culling boxes use S and the tilt; the waves'
// blur is I - (I + S)^-1 (I where S is not finite).
struct CentreFootprint {
    double A[3], B[3], cz, j00, j01, j10, j11;
    double s00, s01, s11, tilt;
    bool finite;
    double det, blur[3];
};
template <class S>
SZ_HD CentreFootprint centre_footprint(const Settings& st, const S* T9, const S* center) {
    CentreFootprint fp;
    const double m1[3] = {double(T9[0]), double(T9[1]), double(T9[2])};
    const double m2[3] = {double(T9[3]), double(T9[4]), double(T9[5])};
    const double m3[3] = {double(T9[6]), double(T9[7]), double(T9[8])};
    const double A[3] = {m2[1] * m3[2] - m2[2] * m3[1], m2[2] * m3[0] - m2[0] * m3[2], m2[0] * m3[1] - m2[1] * m3[0]};
    const double B[3] = {m3[1] * m1[2] - m3[2] * m1[1], m3[2] * m1[0] - m3[0] * m1[2], m3[0] * m1[1] - m3[1] * m1[0]};
    for (int i = 0; i < 3; ++i) {
        fp.A[i] = A[i];
        fp.B[i] = B[i];
    }
    const double C2 = m1[0] * m2[1] - m1[1] * m2[0];
    fp.cz = C2 + double(center[0]) * A[2] + double(center[1]) * B[2];
    const double inv = 1.0 / (fp.cz != 0.0 ? fp.cz : 1e-30);
    fp.j00 = A[0] * inv;
    fp.j01 = B[0] * inv;
    fp.j10 = A[1] * inv;
    fp.j11 = B[1] * inv;
    const double f = st.pixel_filter;
    fp.s00 = f * (fp.j00 * fp.j00 + fp.j01 * fp.j01);
    fp.s01 = f * (fp.j00 * fp.j10 + fp.j01 * fp.j11);
    fp.s11 = f * (fp.j10 * fp.j10 + fp.j11 * fp.j11);
    fp.tilt = sqrt(f) * sqrt(A[2] * A[2] + B[2] * B[2]) * (inv < 0 ? -inv : inv) / LINEAR_LIMIT;
    fp.tilt = fp.tilt < 1.0 ? fp.tilt : 1.0;
    fp.finite = fp.s00 + fp.s11 < 1e30;  // false for NaN and inf too
    fp.det = (1.0 + fp.s00) * (1.0 + fp.s11) - fp.s01 * fp.s01;
    fp.blur[0] = fp.finite ? 1.0 - (1.0 + fp.s11) / fp.det : 1.0;
    fp.blur[1] = fp.finite ? fp.s01 / fp.det : 0.0;
    fp.blur[2] = fp.finite ? 1.0 - (1.0 + fp.s00) / fp.det : 1.0;
    return fp;
}

// Gradient of the waves' blur (v_blur: b00, b01, b11; the off-diagonal counted once) -> A, B (added); returns
// dL/dcz. cz's own dependence on C2, A2, B2 and the centre is the caller's (finalize_grads).
SZ_HD double centre_blur_backward(const Settings& st, const CentreFootprint& fp, const double* v_blur, double* v_A,
                                  double* v_B) {
    if (!fp.finite) return 0.0;
    const double idet = 1.0 / fp.det;
    // blur = I - P, P = [[1 + s11, -s01], [-s01, 1 + s00]] / det, det = (1 + s00)(1 + s11) - s01^2
    const double v_p00 = -v_blur[0], v_p01 = -v_blur[1], v_p11 = -v_blur[2];
    const double v_det = -(v_p00 * (1.0 + fp.s11) - v_p01 * fp.s01 + v_p11 * (1.0 + fp.s00)) * idet * idet;
    const double v_s00 = v_p11 * idet + v_det * (1.0 + fp.s11);
    const double v_s11 = v_p00 * idet + v_det * (1.0 + fp.s00);
    const double v_s01 = -v_p01 * idet - 2.0 * v_det * fp.s01;
    // S = f J J^T
    const double f = st.pixel_filter;
    const double v_j00 = f * (2.0 * fp.j00 * v_s00 + fp.j10 * v_s01);
    const double v_j01 = f * (2.0 * fp.j01 * v_s00 + fp.j11 * v_s01);
    const double v_j10 = f * (2.0 * fp.j10 * v_s11 + fp.j00 * v_s01);
    const double v_j11 = f * (2.0 * fp.j11 * v_s11 + fp.j01 * v_s01);
    // J = [[A0, B0], [A1, B1]] / cz
    const double inv = 1.0 / (fp.cz != 0.0 ? fp.cz : 1e-30);
    v_A[0] += v_j00 * inv;
    v_A[1] += v_j10 * inv;
    v_B[0] += v_j01 * inv;
    v_B[1] += v_j11 * inv;
    return -(fp.j00 * v_j00 + fp.j01 * v_j01 + fp.j10 * v_j10 + fp.j11 * v_j11) * inv;
}

// Screen box (xmin, ymin, xmax, ymax) of the image of x^T (I + S)^-1 x <= r2 in the surfel's plane (S = 0: the
// disc), from the dual conic Q = T diag(r2 (I + S), -1) T^T; +-big where it reaches the camera plane or S is not
// finite (common._conic_box).
template <class S>
SZ_HD void conic_box(const S* T9, S r2, S s00, S s01, S s11, S big, S* b) {
    const bool finite = s00 + s11 < S(1e12);  // false for NaN and inf too
    const S e00 = finite ? S(1) + s00 : S(1), e01 = finite ? s01 : S(0), e11 = finite ? S(1) + s11 : S(1);
    auto Q = [&](int i, int j) {
        const S* a = T9 + 3 * i;
        const S* c = T9 + 3 * j;
        return r2 * (e00 * a[0] * c[0] + e01 * (a[0] * c[1] + a[1] * c[0]) + e11 * a[1] * c[1]) - a[2] * c[2];
    };
    const S q22 = Q(2, 2), q02 = Q(0, 2), q12 = Q(1, 2);
    if (q22 < S(0) && finite) {  // entirely in front of the camera plane
        const S cx = q02 / q22, cy = q12 / q22;
        const S hx = sqrt(smax(q02 * q02 - Q(0, 0) * q22, S(0))) / sabs(q22);
        const S hy = sqrt(smax(q12 * q12 - Q(1, 1) * q22, S(0))) / sabs(q22);
        b[0] = cx - hx; b[1] = cy - hy; b[2] = cx + hx; b[3] = cy + hy;
    } else {
        b[0] = -big; b[1] = -big; b[2] = big; b[3] = big;
    }
}

// Row i of c = K R_cam p + K t, accumulated in double: a scene far from the origin cancels large coordinates against
// the camera's translation (common.project does the same).
template <class S>
SZ_HD double camera_coord(const CameraArgs<S>& cam, const S* mean, int i) {
    return double(cam.KR[3 * i]) * double(mean[0]) + double(cam.KR[3 * i + 1]) * double(mean[1]) +
           double(cam.KR[3 * i + 2]) * double(mean[2]) + double(cam.Kt[i]);
}

// T = [a | b | c] with a = K R_cam (s_u t_u), b = K R_cam (s_v t_v), c = K R_cam p + K t (T9 row-major: row i is
// (a_i, b_i, c_i)); the projected centre c_xy / c_z, the camera depth c_z, the world normal t_w turned to face the
// camera; and the exact screen box of the support (common.screen_boxes: the disc u^2 + v^2 <= 2 ln(255 o) as a
// conic, united with the screen filter's disc, padded for rounding). Returns whether the surfel is visible.
// The support: a contribution is skipped when o exp(-rho/2) < alpha_min, i.e. outside rho <= 2 ln(o / alpha_min).
template <class S>
SZ_HD bool project_surfel(const Settings& st, const CameraArgs<S>& cam, const S* mean, const S* quat, const S* scale, S opacity,
                          S falloff_s, S* T9, S* center, S* depth, S* normal, S* box) {
    S R[9], qn[4], qnorm;
    quat_rotmat(quat, R, qn, qnorm);
    const S* KR = cam.KR;
    for (int i = 0; i < 3; ++i) {
        T9[3 * i + 0] = KR[3 * i] * (scale[0] * R[0]) + KR[3 * i + 1] * (scale[0] * R[3]) + KR[3 * i + 2] * (scale[0] * R[6]);
        T9[3 * i + 1] = KR[3 * i] * (scale[1] * R[1]) + KR[3 * i + 1] * (scale[1] * R[4]) + KR[3 * i + 2] * (scale[1] * R[7]);
        T9[3 * i + 2] = S(camera_coord(cam, mean, i));
    }
    const S cz = T9[8];
    *depth = cz;
    const S d = sabs(cz) > S(1e-12) ? cz : S(1);
    center[0] = T9[2] / d;
    center[1] = T9[5] / d;
    const S facing = R[2] * (mean[0] - cam.eye[0]) + R[5] * (mean[1] - cam.eye[1]) + R[8] * (mean[2] - cam.eye[2]);
    const S flip = facing > S(0) ? S(-1) : S(1);
    normal[0] = R[2] * flip;
    normal[1] = R[5] * flip;
    normal[2] = R[8] * flip;

    const S o = smin(smax(opacity, S(0)), S(1));
    const S log_o = log(smax(o / S(st.alpha_min), S(1e-30)));
    const bool visible = cz > S(st.near) && log_o > S(0);
    const S r2 = log_o > S(0) ? S(support_rho(double(log_o), double(falloff_s))) : S(0);
    const S big = S(double(cam.W > cam.H ? cam.W : cam.H) * 4 + 1e4);
    S b[4];
    conic_box(T9, r2, S(0), S(0), S(0), big, b);  // the disc's image
    if (st.pixel_filter > 0) {
        // no screen filter: the footprint-widened support, bounded as in common.screen_boxes: the conic of the
        // centre's footprint and the disc grown by r footprint sigmas, intersected, then padded by the tilt
        const CentreFootprint fp = centre_footprint(st, T9, center);
        const double tilt = fp.tilt;
        S wide[4];
        conic_box(T9, r2, S(fp.s00), S(fp.s01), S(fp.s11), big, wide);
        const S grow = sqrt(r2 * S(st.pixel_filter));
        b[0] = smax(wide[0], b[0] - grow);
        b[1] = smax(wide[1], b[1] - grow);
        b[2] = smin(wide[2], b[2] + grow);
        b[3] = smin(wide[3], b[3] + grow);
        const S px = (S(FOOTPRINT_PAD) * (b[2] - b[0]) + S(FOOTPRINT_PAD_PX)) * S(tilt);
        const S py = (S(FOOTPRINT_PAD) * (b[3] - b[1]) + S(FOOTPRINT_PAD_PX)) * S(tilt);
        b[0] -= px; b[1] -= py; b[2] += px; b[3] += py;
    } else {
        const S rf = sqrt(r2 / S(st.filter_inv_sq));  // the screen filter's rho2 = F |d|^2 within the support
        b[0] = nan_min(b[0], center[0] - rf);
        b[1] = nan_min(b[1], center[1] - rf);
        b[2] = nan_max(b[2], center[0] + rf);
        b[3] = nan_max(b[3], center[1] + rf);
    }
    for (int k = 0; k < 4; ++k) {
        S v = b[k] != b[k] ? S(0) : b[k];  // nan_to_num, then clamp to +-big
        v = smin(smax(v, -big), big);
        const S pad = S(1e-3) * (S(1) + sabs(v));  // slack for rounding: a box is a cull test, never a cut
        box[k] = k < 2 ? v - pad : v + pad;
    }
    const bool on_screen = box[2] >= S(0.5) && box[0] <= S(cam.W) - S(0.5) && box[3] >= S(0.5) &&
                           box[1] <= S(cam.H) - S(0.5);
    return visible && on_screen;
}

// Gradients of project_surfel's differentiable outputs (T, centre, depth, normal) -> mean, quaternion, scales.
// The facing flip and the box are piecewise constant; the centre divides by c_z only where |c_z| > 1e-12.
template <class S>
SZ_HD void project_backward(const CameraArgs<S>& cam, const S* mean, const S* quat, const S* scale, const S* v_T9,
                            const S* v_center, S v_depth, const S* v_normal, S* v_mean, S* v_quat, S* v_scale) {
    S R[9], qn[4], qnorm;
    quat_rotmat(quat, R, qn, qnorm);
    const S* KR = cam.KR;
    S c[3], v_a[3], v_b[3], v_c[3];
    for (int i = 0; i < 3; ++i) {
        c[i] = S(camera_coord(cam, mean, i));
        v_a[i] = v_T9[3 * i];
        v_b[i] = v_T9[3 * i + 1];
        v_c[i] = v_T9[3 * i + 2];
    }
    v_c[2] += v_depth;
    if (sabs(c[2]) > S(1e-12)) {
        const S inv = S(1) / c[2];
        v_c[0] += v_center[0] * inv;
        v_c[1] += v_center[1] * inv;
        v_c[2] -= (v_center[0] * c[0] + v_center[1] * c[1]) * inv * inv;
    } else {
        v_c[0] += v_center[0];
        v_c[1] += v_center[1];
    }
    // x = KR y  =>  v_y = KR^T v_x
    S v_su_tu[3], v_sv_tv[3];
    for (int j = 0; j < 3; ++j) {
        v_mean[j] = KR[j] * v_c[0] + KR[3 + j] * v_c[1] + KR[6 + j] * v_c[2];
        v_su_tu[j] = KR[j] * v_a[0] + KR[3 + j] * v_a[1] + KR[6 + j] * v_a[2];
        v_sv_tv[j] = KR[j] * v_b[0] + KR[3 + j] * v_b[1] + KR[6 + j] * v_b[2];
    }
    v_scale[0] = v_su_tu[0] * R[0] + v_su_tu[1] * R[3] + v_su_tu[2] * R[6];
    v_scale[1] = v_sv_tv[0] * R[1] + v_sv_tv[1] * R[4] + v_sv_tv[2] * R[7];
    const S facing = R[2] * (mean[0] - cam.eye[0]) + R[5] * (mean[1] - cam.eye[1]) + R[8] * (mean[2] - cam.eye[2]);
    const S flip = facing > S(0) ? S(-1) : S(1);
    S v_R[9];  // dL/dR, row-major: column 0 from a, column 1 from b, column 2 from the normal
    for (int i = 0; i < 3; ++i) {
        v_R[3 * i] = scale[0] * v_su_tu[i];
        v_R[3 * i + 1] = scale[1] * v_sv_tv[i];
        v_R[3 * i + 2] = flip * v_normal[i];
    }
    const S w = qn[0], x = qn[1], y = qn[2], z = qn[3];
    S v_q[4];
    v_q[0] = S(2) * (-z * v_R[1] + y * v_R[2] + z * v_R[3] - x * v_R[5] - y * v_R[6] + x * v_R[7]);
    v_q[1] = S(2) * (y * v_R[1] + z * v_R[2] + y * v_R[3] - S(2) * x * v_R[4] - w * v_R[5] + z * v_R[6] + w * v_R[7] -
                    S(2) * x * v_R[8]);
    v_q[2] = S(2) * (-S(2) * y * v_R[0] + x * v_R[1] + w * v_R[2] + x * v_R[3] + z * v_R[5] - w * v_R[6] + z * v_R[7] -
                    S(2) * y * v_R[8]);
    v_q[3] = S(2) * (-S(2) * z * v_R[0] - w * v_R[1] + x * v_R[2] + w * v_R[3] - S(2) * z * v_R[4] + y * v_R[5] +
                    x * v_R[6] + y * v_R[7]);
    // q / max(|q|, eps): (I - qn qn^T) / |q| above eps, I / eps below (torch.clamp_min passes no gradient)
    if (qnorm > S(1e-12)) {
        const S dot = v_q[0] * w + v_q[1] * x + v_q[2] * y + v_q[3] * z;
        for (int i = 0; i < 4; ++i) v_quat[i] = (v_q[i] - qn[i] * dot) / qnorm;
    } else {
        for (int i = 0; i < 4; ++i) v_quat[i] = v_q[i] / S(1e-12);
    }
}

// ---- per-surfel set-up ------------------------------------------------------------------------------------------
// T9: rows m1, m2, m3 of M = K [R s_u t_u | R s_v t_v | R p + t] (row-major 3x3). The pixel planes are
// h_x = x m3 - m1 and h_y = y m3 - m2, and c = h_x x h_y = x (m2 x m3) + y (m3 x m1) + m1 x m2: affine in (x, y).
// Expanding it around the projected centre (in double, once per surfel) turns the per-pixel cross product into
// 6 multiply-adds and removes the cancellation the per-pixel form suffers far from the image origin.
// The pixel planes' coefficients in double, c(x, y) = (x - cx) A + (y - cy) B + C with C centred, and the power of
// two `scale` that brings the largest of them into [0.5, 1). The pixels use c only through ratios (u = c0 / c2,
// J = N / c2^2, the hit and linearisation tests) that do not change when A, B, C are scaled together, and a power of
// two changes no rounding: the result is the same bit for bit, but the anti-aliased footprint's products (A0 C2, ...)
// of a surfel some 1e9 px across no longer overflow float. scale is 1 where the coefficients are 0 or not finite.
struct PlaneCoeffs {
    double A[3], B[3], C[3], scale;
};
template <class S>
SZ_HD PlaneCoeffs plane_coeffs(const S* T9, const S* center) {
    const double m1[3] = {double(T9[0]), double(T9[1]), double(T9[2])};
    const double m2[3] = {double(T9[3]), double(T9[4]), double(T9[5])};
    const double m3[3] = {double(T9[6]), double(T9[7]), double(T9[8])};
    PlaneCoeffs p;
    p.A[0] = m2[1] * m3[2] - m2[2] * m3[1]; p.A[1] = m2[2] * m3[0] - m2[0] * m3[2]; p.A[2] = m2[0] * m3[1] - m2[1] * m3[0];
    p.B[0] = m3[1] * m1[2] - m3[2] * m1[1]; p.B[1] = m3[2] * m1[0] - m3[0] * m1[2]; p.B[2] = m3[0] * m1[1] - m3[1] * m1[0];
    const double cx = double(center[0]), cy = double(center[1]);
    double C[3] = {m1[1] * m2[2] - m1[2] * m2[1], m1[2] * m2[0] - m1[0] * m2[2], m1[0] * m2[1] - m1[1] * m2[0]};
    double top = 0.0;
    for (int i = 0; i < 3; ++i) {
        p.C[i] = C[i] + cx * p.A[i] + cy * p.B[i];
        top = smax(top, smax(sabs(p.A[i]), smax(sabs(p.B[i]), sabs(p.C[i]))));
    }
    p.scale = 1.0;
    if (top > 0.0 && top < INFINITY) {  // false for NaN too
        int e;
        frexp(top, &e);
        p.scale = ldexp(1.0, -e);
    }
    return p;
}

// T9: rows m1, m2, m3 of M = K [R s_u t_u | R s_v t_v | R p + t] (row-major 3x3). The pixel planes are
// h_x = x m3 - m1 and h_y = y m3 - m2, and c = h_x x h_y = x (m2 x m3) + y (m3 x m1) + m1 x m2: affine in (x, y).
// Expanding it around the projected centre (in double, once per surfel) turns the per-pixel cross product into
// 6 multiply-adds and removes the cancellation the per-pixel form suffers far from the image origin. A, B, C are
// stored scaled (plane_coeffs); finalize_grads scales their gradients back.
template <class S>
SZ_HD void prepare_geom(const Settings& st, const S* T9, const S* center, S depth, S opacity, S falloff_s,
                        Geom<S>& g) {
    const PlaneCoeffs p = plane_coeffs(T9, center);
    for (int i = 0; i < 3; ++i) {
        g.A[i] = S(p.A[i] * p.scale);
        g.B[i] = S(p.B[i] * p.scale);
        g.C[i] = S(p.C[i] * p.scale);
        g.m3[i] = T9[6 + i];
    }
    g.cx = center[0];
    g.cy = center[1];
    g.zc = depth;
    g.o = opacity;
    g.s = falloff_s;
    g.blur[0] = g.blur[1] = g.blur[2] = S(0);
    if (st.pixel_filter > 0) {
        const CentreFootprint fp = centre_footprint(st, T9, center);
        for (int i = 0; i < 3; ++i) g.blur[i] = S(fp.blur[i]);
    }
}

// ---- forward of one (surfel, pixel) pair ------------------------------------------------------------------------
template <class S>
struct PairEval {
    S dx, dy;      // pixel centre minus projected centre
    S c0, c1, c2;  // c = h_x x h_y
    S u, v, z;     // local coordinates used for colour (0 where the filter wins; the footprint's P x when
                   // anti-aliased) and the depth there
    S rho;         // rho = u^2 + v^2 at the hit, or the screen filter's (anti-aliased: the footprint's q)
    S ex, raw;     // f(rho) (anti-aliased: det(I + S)^-1/2 f(q)) and o * ex before the clamp
    S alpha;       // final alpha, 0 where skipped (alpha < alpha_min or z < near)
    bool use3;     // the ray-splat hit (rho3d) won over the screen filter (rho2d); always, when anti-aliased
    // anti-aliased only (see eval_pair_filtered): 1 / c2, the hit x, the Jacobian d(u, v)/d(pixel),
    // P = (I + S)^-1 (p01 once) and 1 / det(I + S)
    S inv, xu, xv, j00, j01, j10, j11, p00, p01, p11, idet;
};

// Products and sums of the blend decision, each rounded on its own: on a GPU the compiler may otherwise fuse a
// multiply and an add into an fma in one inlined copy and not in another, and the forward and backward kernels,
// which both evaluate every pair, could then disagree on whether a pair on a threshold is blended. The host loops
// evaluate alphas in one non-inlined function (and the host emulation is built without contraction).
#ifdef __CUDA_ARCH__
SZ_HD float rmul(float a, float b) { return __fmul_rn(a, b); }
SZ_HD float radd(float a, float b) { return __fadd_rn(a, b); }
SZ_HD double rmul(double a, double b) { return __dmul_rn(a, b); }
SZ_HD double radd(double a, double b) { return __dadd_rn(a, b); }
#else
template <class S> SZ_HD S rmul(S a, S b) { return a * b; }
template <class S> SZ_HD S radd(S a, S b) { return a + b; }
#endif

// ---- the kernel falloff, a declared part of the appearance contract (common.falloff is its twin) ----------------
// f(rho) over rho = u^2 + v^2 in sigmas squared (anti-aliased: the footprint's q), one struct per falloff: the Gaussian
// exp(-rho/2) where the surfel's falloff exponent s is 0, else the Beta kernel (1 - s rho/2)_+^(1/s), 0 < s <= 1:
// Deformable Beta Splatting's (1 - r^2)^b with b = 1/s and r^2 = s rho/2, 0 beyond rho = 2/s, the Gaussian again as
// s -> 0. value(rho, s) is f; dlog(rho, s, d_rho, d_s) gives d ln f / d rho and d ln f / d s where f > 0.
// with_falloff picks one per surfel, at compile time for its pairs: the pixel loops stay branch-free.
struct GaussianFalloff {
    template <class S>
    SZ_HD static S value(S rho, S) {
        return sz_exp(rmul(S(-0.5), rho));
    }
    // s = 0: the Beta kernel's d ln f / d s series at its first term, -rho^2/8 (the Gaussian's pairs pay no more than
    // that), so that a surfel can move from the Gaussian into the Beta family
    template <class S>
    SZ_HD static void dlog(S rho, S, S& d_rho, S& d_s) {
        d_rho = S(-0.5);
        d_s = S(-0.125) * rho * rho;
    }
};

struct BetaFalloff {
    template <class S>
    SZ_HD static S value(S rho, S s) {
        const S x = rmul(rmul(S(0.5), s), rho);  // ln f = log1p(-x) / s: accurate for a small s, where w = 1 - x
        const S f = sz_exp(sz_log1m(x < S(1) ? x : S(0)) / s);  //   rounds to 1
        return x < S(1) ? f : S(0);
    }
    // -1/(2w) and -ln(w)/s^2 - rho/(2 s w), w = 1 - x, x = s rho/2. The second is a series where x is small (its two
    // terms cancel): -(rho/2)^2 (1/2 + 2x/3 + 3x^2/4 + 4x^3/5), which at s = 0 is -rho^2/8, the Gaussian's own.
    template <class S>
    SZ_HD static void dlog(S rho, S s, S& d_rho, S& d_s) {
        const S x = rmul(rmul(S(0.5), s), rho), h = S(0.5) * rho;
        const S w = S(1) - x;
        const S ws = w > S(1e-30) ? w : S(1e-30);
        const S series = -(h * h) * (S(0.5) + x * (S(2.0 / 3.0) + x * (S(0.75) + x * S(0.8))));
        const S ss = s > S(0) ? s : S(1);
        const S closed = -sz_log1m(x < S(1) ? x : S(0)) / (ss * ss) - h / (ss * ws);
        d_s = x < S(1e-2) ? series : closed;
        d_rho = S(-0.5) / ws;
    }
};

// Calls body(GaussianFalloff{}) or body(BetaFalloff{}) for a surfel of falloff exponent s: the one place that branches
// on a surfel's falloff (once per surfel, or per pair on a GPU, where every thread of a warp meets the same surfel).
template <class S, class Body>
SZ_HD void with_falloff(S s, Body&& body) {
    if (s > S(0))
        body(BetaFalloff{});
    else
        body(GaussianFalloff{});
}

// The pixel's ray against the surfel's plane: d = pixel - centre, c = h_x x h_y, whether the ray hits the plane and
// inv = 1 / c2 where it does (else 0). Branch-free, as everything a pixel loop calls, so that the loop vectorises.
template <class S>
struct PixelRay {
    S dx, dy, c0, c1, c2, inv;
    bool hit;
};
template <class S>
SZ_HD PixelRay<S> pixel_ray(const Settings& st, const Geom<S>& g, S x, S y) {
    PixelRay<S> r;
    r.dx = radd(x, -g.cx);
    r.dy = radd(y, -g.cy);
    r.c0 = radd(radd(rmul(r.dx, g.A[0]), rmul(r.dy, g.B[0])), g.C[0]);
    r.c1 = radd(radd(rmul(r.dx, g.A[1]), rmul(r.dy, g.B[1])), g.C[1]);
    r.c2 = radd(radd(rmul(r.dx, g.A[2]), rmul(r.dy, g.B[2])), g.C[2]);
    // reference: |cz| > parallel_eps * max(|cx|, |cy|) and cz != 0 (a ray almost parallel to the plane misses
    // it); the first test already fails for cz == 0. Each select below depends on one comparison only: GCC turns
    // selects on combined conditions into branches, and the pixel loop stops vectorising.
    r.hit = sabs(r.c2) > rmul(S(st.parallel_eps), smax(sabs(r.c0), sabs(r.c1)));
    S inv = S(1) / (r.hit ? r.c2 : S(1));  // a division inside a select would not be speculated (vectorised)
    r.inv = r.hit ? inv : S(0);
    return r;
}

// The blended alpha of o times the falloff (raw) at depth z: clamped at alpha_max, 0 below alpha_min or nearer
// than the near plane.
template <class S>
SZ_HD S pair_alpha(const Settings& st, S raw, S z) {
    const S amax = S(st.alpha_max);
    S a = raw < amax ? raw : amax;
    a = a >= S(st.alpha_min) ? a : S(0);
    return z >= S(st.near) ? a : S(0);
}

template <class F = GaussianFalloff, class S>
SZ_HD void eval_pair(const Settings& st, const Geom<S>& g, S x, S y, PairEval<S>& e) {
    const PixelRay<S> ray = pixel_ray(st, g, x, y);
    const S dx = ray.dx, dy = ray.dy, c0 = ray.c0, c1 = ray.c1, c2 = ray.c2, inv = ray.inv;
    const bool hit = ray.hit;
    S uu = rmul(c0, inv), vv = rmul(c1, inv);
    S rho3 = hit ? radd(rmul(uu, uu), rmul(vv, vv)) : S(INFINITY);
    S rho2 = rmul(S(st.filter_inv_sq), radd(rmul(dx, dx), rmul(dy, dy)));
    bool use3 = rho3 <= rho2;
    S rho = use3 ? rho3 : rho2;
    S u = use3 ? uu : S(0);
    S v = use3 ? vv : S(0);
    S z = use3 ? radd(radd(rmul(g.m3[0], u), rmul(g.m3[1], v)), g.m3[2]) : g.zc;
    S ex = F::value(rho, g.s);
    S raw = rmul(g.o, ex);
    e.dx = dx; e.dy = dy; e.c0 = c0; e.c1 = c1; e.c2 = c2;
    e.u = u; e.v = v; e.z = z; e.rho = rho; e.ex = ex; e.raw = raw;
    e.alpha = pair_alpha(st, raw, z);
    e.use3 = use3;
}

// Anti-aliased (st.pixel_filter > 0): the pixel's Gaussian footprint, variance f = pixel_filter, is N(x, S) in the
// surfel's frame around the hit x, S = f J J^T, J = d(u, v)/d(pixel). With P = (I + S)^-1 the surfel's falloff
// averaged over the footprint is det(I + S)^-1/2 exp(-x^T P x / 2), and its colour the mean under N(P x, I - P): a
// wave a cos(k.x + phi) becomes a exp(-k^T (I - P) k / 2) cos(k.(P x) + phi). The waves' blur I - P is taken at
// the projected centre, once per surfel (Geom::blur, fold_gains); the rest per pixel. Same as
// reference.footprint_filter.
// Pairs with tr S > 1 / alpha_min^2 are culled (their gain alone is below alpha_min). Branch-free.
// J = [[A0 - x0 A2, B0 - x0 B2], [A1 - x1 A2, B1 - x1 B2]] / c2 = N / c2^2, and with c = dx A + dy B + C the
// column x row products cancel: N00 = A0 c2 - A2 c0 = dy (A0 B2 - A2 B0) + (A0 C2 - A2 C0) depends on the row only,
// N01 = dx (B0 A2 - B2 A0) + (B0 C2 - B2 C0) on the column only (N10, N11 alike), so a pixel loop pays one product
// for each. P x and x^T P x are taken as adj(I + S) x / det: the division runs beside the products.
template <class F = GaussianFalloff, class S>
SZ_HD void eval_pair_filtered(const Settings& st, const Geom<S>& g, S x, S y, PairEval<S>& e) {
    const PixelRay<S> ray = pixel_ray(st, g, x, y);
    const S dx = ray.dx, dy = ray.dy, c0 = ray.c0, c1 = ray.c1, c2 = ray.c2, inv = ray.inv;
    const bool hit = ray.hit;
    S xu = rmul(c0, inv), xv = rmul(c1, inv);
    const S ab0 = radd(rmul(g.A[0], g.B[2]), -rmul(g.A[2], g.B[0]));  // per surfel: loop invariants
    const S ab1 = radd(rmul(g.A[1], g.B[2]), -rmul(g.A[2], g.B[1]));
    const S n00 = radd(rmul(dy, ab0), radd(rmul(g.A[0], g.C[2]), -rmul(g.A[2], g.C[0])));
    const S n10 = radd(rmul(dy, ab1), radd(rmul(g.A[1], g.C[2]), -rmul(g.A[2], g.C[1])));
    const S n01 = radd(rmul(dx, -ab0), radd(rmul(g.B[0], g.C[2]), -rmul(g.B[2], g.C[0])));
    const S n11 = radd(rmul(dx, -ab1), radd(rmul(g.B[1], g.C[2]), -rmul(g.B[2], g.C[1])));
    const S inv2 = rmul(inv, inv);
    S j00 = rmul(n00, inv2), j01 = rmul(n01, inv2), j10 = rmul(n10, inv2), j11 = rmul(n11, inv2);
    const S f = S(st.pixel_filter);
    S s00 = rmul(f, radd(rmul(j00, j00), rmul(j01, j01)));
    S s01 = rmul(f, radd(rmul(j00, j10), rmul(j01, j11)));
    S s11 = rmul(f, radd(rmul(j10, j10), rmul(j11, j11)));
    bool keep = radd(s00, s11) <= S(1.0 / (st.alpha_min * st.alpha_min));  // false for NaN and inf too
    // the linearisation holds: the footprint is small next to the distance to the vanishing line c2 = 0
    const S lc2 = rmul(S(LINEAR_LIMIT), c2);
    bool linear = rmul(f, radd(rmul(g.A[2], g.A[2]), rmul(g.B[2], g.B[2]))) <= rmul(lc2, lc2);
    s00 = keep ? s00 : S(0);
    s01 = keep ? s01 : S(0);
    s11 = keep ? s11 : S(0);
    const S a00 = radd(S(1), s11), a11 = radd(S(1), s00);  // adj(I + S) = [[a00, -s01], [-s01, a11]]
    S det = radd(rmul(a11, a00), -rmul(s01, s01));
    S idet = S(1) / det;
    const S hu = radd(rmul(a00, xu), -rmul(s01, xv)), hv = radd(rmul(a11, xv), -rmul(s01, xu));  // adj x
    S q = rmul(radd(rmul(xu, hu), rmul(xv, hv)), idet);
    S mu = rmul(hu, idet), mv = rmul(hv, idet);
    S z = radd(radd(rmul(g.m3[0], mu), rmul(g.m3[1], mv)), g.m3[2]);
    S gain = sqrt(idet);
    gain = hit ? gain : S(0);
    gain = keep ? gain : S(0);
    gain = linear ? gain : S(0);  // one comparison per select: combined conditions become branches (no vectors)
    S ex = rmul(gain, F::value(q, g.s));
    S raw = rmul(g.o, ex);
    e.dx = dx; e.dy = dy; e.c0 = c0; e.c1 = c1; e.c2 = c2;
    e.u = mu; e.v = mv; e.z = z; e.rho = q; e.ex = ex; e.raw = raw;
    e.alpha = pair_alpha(st, raw, z);
    e.use3 = true;
    e.xu = xu; e.xv = xv; e.j00 = j00; e.j01 = j01; e.j10 = j10; e.j11 = j11;
    e.p00 = rmul(a00, idet); e.p01 = rmul(-s01, idet); e.p11 = rmul(a11, idet); e.idet = idet; e.inv = inv;
}

// Either evaluation, by the settings (a branch every thread of a launch takes the same way).
template <class S>
SZ_HD void eval_pair_any(const Settings& st, const Geom<S>& g, S x, S y, PairEval<S>& e) {
    // the filter outside, the falloff inside: the two falloffs' filtered pairs share their footprint's code
    if (st.pixel_filter > 0)
        with_falloff(g.s, [&](auto falloff) SZ_INLINE_LAMBDA {
            eval_pair_filtered<decltype(falloff)>(st, g, x, y, e);
        });
    else
        with_falloff(g.s, [&](auto falloff) SZ_INLINE_LAMBDA { eval_pair<decltype(falloff)>(st, g, x, y, e); });
}

// ---- appearance: what a surfel looks like at a pair ---------------------------------------------------------
// An appearance gives, at the point (u, v) of the surfel where a pair's colour is taken (the ray's hit; (0, 0) where
// the screen filter wins; anti-aliased the footprint's centre P x), an rgb colour and an opacity gain g(u, v) in
// [0, 1] that multiplies o times the falloff. It is a composition of kinds (Appearance, at the end of this section):
// their colours add up, clamped at 0 after the sum (the clamp belongs to the blend, blend_backward_colour), and their
// gains multiply. Each kind is one struct in its own section below, with its twin in rasterizers/reference.py
// (KIND_TWINS) and its fields in the Surfels table (splatzoo/types.py, `kind=`); it declares:
//   - its fields: SZ_KIND_FIELD_MEMBERS over the list the generator writes for it (surfel_fields.h,
//     SZ_KIND_FIELDS_<KIND>): a pointer to one surfel's row of each field, by the field's table name; Grads, the
//     pointers v_<name> its gradients go to; bind_fields / bind_grads, which point them at surfel i;
//   - bind(args, i, prepared): its fields and sizes for surfel i (prepared: its slice of the surfel's prepared row);
//   - dense_slots(K), scatter_slots(K, T): its blocks of the slot row. Dense slots are accumulated through acc, the
//     same ones in the same order at every pair (the CUDA warp sums and register row rely on it); scatter slots differ
//     from pixel to pixel (acc.scatter: one atomic per lane);
//   - prepared_width(K, T, filtered), prepare(blur, out): a per-surfel set-up that the prepare step makes once per
//     render into the surfel's prepared row (the texture's prefilter), which bind then reads;
//   - fold_values(K), fold_factors(K), fold(g, values, factors), unfold(row, dense): anti-aliased, the CPU loop lets
//     a kind fold its per-surfel footprint factors into what the pixels read (the waves' gains into their amplitudes)
//     once per (surfel, tile), with the blur left out of the pixels' calls: values holds the folded copies of its
//     fields, factors what unfold then applies to its slots (two buffers: GCC vectorises the fold loop, and so
//     rounds it, as it did when the waves' two arrays were separate);
//   - Cache<KMAX>: what add_colour keeps of a pair for backward;
//   - has_gain(), gain(u, v): its opacity gain (has_gain() false: none, and gain is never called);
//   - add_colour<KMAX>(u, v, rgb, blur, cache): adds its rgb at (u, v) (blur: Geom::blur when anti-aliased and not
//     folded, else nullptr) and returns its gain (1 without one);
//   - backward<KMAX>(u, v, v_col, v_lngain, blur, cache, acc, dense, scatter, v_u, v_v): dL/d rgb (v_col, the
//     clamp's gate applied) and dL/d ln g (v_lngain) -> its slots (its blocks start at dense and scatter) and
//     dL/d(u, v) (added);
//   - finalize(Gs, dense, scatter, filtered, b, v_blur, grads): its blocks of a summed slot row -> its fields'
//     gradients; anti-aliased (b: the blur the pixels used) its footprint factors' gradients add into v_blur.
// KMAX >= 0 promises that no surfel has more than KMAX waves (the wave bank unrolls its loop: compile-time slots).
// Nothing outside a kind's section names it: the composition, the tile loops and the bindings take the kinds from the
// generated SZ_APPEARANCE_KINDS list.

// A kind's field members, from its generated list FIELDS (X(name, row), row in terms of the batch's K and T).
#define SZ_KIND_POINTER(name, row) const S* name;
#define SZ_KIND_GRADIENT(name, row) S* v_##name;
#define SZ_KIND_BIND(name, row) name = a.name + i * int64_t(row);
#define SZ_KIND_BIND_GRAD(name, row) v.v_##name = a.v_##name + i * int64_t(row);
#define SZ_KIND_FIELD_MEMBERS(FIELDS)                                                                              \
    FIELDS(SZ_KIND_POINTER)                                                                                        \
    struct Grads {                                                                                                 \
        FIELDS(SZ_KIND_GRADIENT)                                                                                   \
    };                                                                                                             \
    template <class Args>                                                                                          \
    SZ_HD void bind_fields(const Args& a, int64_t i, int K, int T) {                                               \
        (void)K;                                                                                                   \
        (void)T;                                                                                                   \
        FIELDS(SZ_KIND_BIND)                                                                                       \
    }                                                                                                              \
    template <class Args>                                                                                          \
    SZ_HD static Grads bind_grads(const Args& a, int64_t i, int K, int T) {                                        \
        (void)K;                                                                                                   \
        (void)T;                                                                                                   \
        Grads v;                                                                                                   \
        FIELDS(SZ_KIND_BIND_GRAD)                                                                                  \
        return v;                                                                                                  \
    }

// The pair's opacity gain into its alpha (after eval_pair*): ex and raw take the factor, the blend decision is made
// again. The tile loops call it only for surfels whose appearance has a gain (Appearance::has_gain), so the others
// keep their exact values.
template <class S>
SZ_HD void apply_opacity_gain(const Settings& st, const Geom<S>& g, S gain, PairEval<S>& e) {
    e.ex = rmul(e.ex, gain);
    e.raw = rmul(g.o, e.ex);
    e.alpha = pair_alpha(st, e.raw, e.z);
}

// ---- kind: the wave bank (kind 0; reference.WaveBankTwin) -------------------------------------------------------
// rgb = c0 + sum_k a_k g_k cos(k_k . (u, v) + phi_k): g_k = 1, or anti-aliased the footprint's gain of wave k,
// wave_gain; no opacity gain. Dense slots: dL/d c0 (3), then per wave d k_x, d k_y, d phi (the wave's phase only),
// d a (3). Anti-aliased, a wave's gain exp(-k^T b k / 2) has the same blur b (the surfel's) at every pixel, so its
// gradients into k and b are per-surfel factors times the sum over pixels of dL/d gain x gain, which is a . (d a):
// finalize applies them. The pixels only ever see a wave's gain times its amplitude.
constexpr int G_PER_WAVE = 6;
// Waves per surfel whose sin/cos the backward keeps on the stack (more are recomputed, same values). On a GPU the
// stack is local memory, still cheaper than recomputing (measured: K=4 backward 17.3 ms without, 14.4 ms with).
constexpr int SINCOS_CACHE = 32;

// Runs body(k) for the waves k < K. KMAX >= 0 promises K <= KMAX: the loop is unrolled with compile-time indices,
// so per-wave arrays and gradient slots can live in registers (the CUDA backward's slot row).
template <int KMAX, class F>
SZ_HD void for_each_wave(int K, F&& body) {
    if constexpr (KMAX < 0) {
        for (int k = 0; k < K; ++k) body(k);
    } else {
#ifdef __CUDA_ARCH__
#pragma unroll
#endif
        for (int k = 0; k < KMAX; ++k)
            if (k < K) body(k);
    }
}

// Footprint attenuation of wave (kx, ky) under the blur (b00, b01, b11): exp(-k^T b k / 2).
template <class S>
SZ_HD S wave_gain(const S* blur, S kx, S ky) {
    return sz_exp(S(-0.5) * (blur[0] * kx * kx + S(2) * blur[1] * kx * ky + blur[2] * ky * ky));
}

// Every wave's footprint gain for one anti-aliased surfel (its blur is the same at all its pixels): gains[k], and
// the amplitudes times them, folded[3k + i] = gains[k] wa[3k + i].
template <class S>
SZ_HD void fold_gains(const Geom<S>& g, const S* wv, const S* wa, int K, S* gains, S* folded) {
    for (int k = 0; k < K; ++k) {
        gains[k] = wave_gain(g.blur, wv[2 * k], wv[2 * k + 1]);
        for (int i = 0; i < 3; ++i) folded[3 * k + i] = gains[k] * wa[3 * k + i];
    }
}

template <class S>
struct WaveBank {
    SZ_KIND_FIELD_MEMBERS(SZ_KIND_FIELDS_WAVE_BANK)  // base_color [3], wave_vectors [K,2], wave_phases [K],
                                                     // wave_amplitudes [K,3]
    int K;           // waves in use: the surfel's first K (Surfels.wave_counts)
    int row_K;       // the batch's K: the rows' stride and the dense block's layout
    const S* gains;  // folded (fold): each wave's footprint gain, which wave_amplitudes then carries; else nullptr

    // each wave's sin, cos (times the footprint gain) and gain at the pair, for the backward (when K fits)
    template <int KMAX>
    struct Cache {
        static constexpr int N = KMAX >= 0 ? (KMAX > 0 ? KMAX : 1) : SINCOS_CACHE;
        S sn[N], cs[N], gain[N];
    };
    template <int KMAX>
    SZ_HD bool caches(const Cache<KMAX>* c) const {
        return c != nullptr && (KMAX >= 0 || K <= SINCOS_CACHE);
    }

    SZ_HD static constexpr int dense_slots(int K) { return 3 + G_PER_WAVE * K; }
    SZ_HD static constexpr int scatter_slots(int, int) { return 0; }
    SZ_HD static constexpr int prepared_width(int, int, bool) { return 0; }
    SZ_HD static constexpr int fold_values(int K) { return 3 * K; }
    SZ_HD static constexpr int fold_factors(int K) { return K; }
    SZ_HD static constexpr bool has_gain() { return false; }
    SZ_HD S gain(S, S) const { return S(1); }

    template <class Args>
    SZ_HD void bind(const Args& a, int64_t i, const S*) {
        bind_fields(a, i, a.K, a.TS);
        row_K = a.K;
        K = a.wcount ? a.wcount[i] : a.K;
        gains = nullptr;
    }
    SZ_HD void prepare(const S*, S*) const {}

    // Every wave's footprint gain (g.blur) in factors and the amplitudes times them in values, which the pixels read
    // in place of the amplitudes.
    SZ_HD void fold(const Geom<S>& g, S* values, S* factors) {
        fold_gains(g, wave_vectors, wave_amplitudes, K, factors, values);
        wave_amplitudes = values;
        gains = factors;
    }
    // d(gain a)/da = gain, on the amplitude slots of the pixels' sums
    SZ_HD void unfold(S* row, int dense) const {
        if (gains == nullptr) return;
        for (int k = 0; k < K; ++k)
            for (int j = 3; j < 6; ++j) row[dense + 3 + G_PER_WAVE * k + j] *= gains[k];
    }

    template <int KMAX>
    SZ_HD S add_colour(S u, S v, S rgb[3], const S* blur, Cache<KMAX>* c) const {
        const S *base = base_color, *wv = wave_vectors, *wp = wave_phases, *wa = wave_amplitudes;
        const bool keep = caches(c);
        S r = rgb[0] + base[0], gg = rgb[1] + base[1], b = rgb[2] + base[2];
        for_each_wave<KMAX>(K, [&](int k) {
            S sn, cs;
            sz_sincos(u * wv[2 * k] + v * wv[2 * k + 1] + wp[k], sn, cs);
            if (blur) {
                const S gk = wave_gain(blur, wv[2 * k], wv[2 * k + 1]);
                if (keep) c->gain[k] = gk;
                cs *= gk;  // sn is only kept for the backward, which multiplies by the gain itself
            }
            if (keep) {  // kept for the backward, which needs both
                c->sn[k] = sn;
                c->cs[k] = cs;
            }
            r += cs * wa[3 * k];
            gg += cs * wa[3 * k + 1];
            b += cs * wa[3 * k + 2];
        });
        rgb[0] = r;
        rgb[1] = gg;
        rgb[2] = b;
        return S(1);
    }

    template <int KMAX, class Acc>
    SZ_HD void backward(S u, S v, const S v_col[3], S, const S* blur, const Cache<KMAX>* c, Acc& acc, int dense, int,
                        S& v_u, S& v_v) const {
        const S *wv = wave_vectors, *wp = wave_phases, *wa = wave_amplitudes;
        const bool cached = caches(c);
        acc(dense + 0, v_col[0]);
        acc(dense + 1, v_col[1]);
        acc(dense + 2, v_col[2]);
        const bool filtered = blur != nullptr;
        for_each_wave<KMAX>(K, [&](int k) {
            S sn, cs, gk = S(1);  // cs: the wave's factor in the colour, gain times cos
            if (cached) {
                sn = c->sn[k];
                cs = c->cs[k];
                if (filtered) gk = c->gain[k];
            } else {
                sz_sincos(u * wv[2 * k] + v * wv[2 * k + 1] + wp[k], sn, cs);
                if (filtered) {
                    gk = wave_gain(blur, wv[2 * k], wv[2 * k + 1]);
                    cs *= gk;
                }
            }
            S v_cos = v_col[0] * wa[3 * k] + v_col[1] * wa[3 * k + 1] + v_col[2] * wa[3 * k + 2];
            S v_phase = -sn * gk * v_cos;  // d/d(phase)
            int o = dense + 3 + G_PER_WAVE * k;
            acc(o + 0, v_phase * u);
            acc(o + 1, v_phase * v);
            acc(o + 2, v_phase);
            acc(o + 3, cs * v_col[0]);
            acc(o + 4, cs * v_col[1]);
            acc(o + 5, cs * v_col[2]);
            v_u += v_phase * wv[2 * k];
            v_v += v_phase * wv[2 * k + 1];
        });
    }

    // anti-aliased, the gains exp(-k^T b k / 2) with b the blur the pixels used (Geom::blur, rounded to S):
    // d/dk = -gain b k, d/db = -gain k k^T / 2, times the summed dL/d gain x gain = a . (dL/da)
    template <class R>
    SZ_HD void finalize(const R* Gs, int dense, int, bool filtered, const double* b, double* v_blur,
                        const Grads& v) const {
        const int K = row_K;  // every wave's gradients (those beyond the surfel's count are 0)
        const S *wv = wave_vectors, *wa = wave_amplitudes;
        for (int i = 0; i < 3; ++i) v.v_base_color[i] = S(Gs[dense + i]);
        for (int k = 0; k < K; ++k) {
            const R* w = Gs + dense + 3 + G_PER_WAVE * k;
            double v_kx = double(w[0]), v_ky = double(w[1]);
            if (filtered) {
                const double v_g = double(wa[3 * k]) * double(w[3]) + double(wa[3 * k + 1]) * double(w[4]) +
                                   double(wa[3 * k + 2]) * double(w[5]);
                const double kx = double(wv[2 * k]), ky = double(wv[2 * k + 1]);
                v_kx -= v_g * (b[0] * kx + b[1] * ky);
                v_ky -= v_g * (b[1] * kx + b[2] * ky);
                v_blur[0] -= 0.5 * v_g * kx * kx;
                v_blur[1] -= v_g * kx * ky;
                v_blur[2] -= 0.5 * v_g * ky * ky;
            }
            v.v_wave_vectors[2 * k] = S(v_kx);
            v.v_wave_vectors[2 * k + 1] = S(v_ky);
            v.v_wave_phases[k] = S(w[2]);
            v.v_wave_amplitudes[3 * k] = S(w[3]);
            v.v_wave_amplitudes[3 * k + 1] = S(w[4]);
            v.v_wave_amplitudes[3 * k + 2] = S(w[5]);
        }
    }
};

// ---- kind: the texture (reference.TextureTwin) ------------------------------------------------------------------
// T x T RGBA texels over (u, v) in [-TEXTURE_RADIUS, TEXTURE_RADIUS]^2, texel (r, c) centred at -R + (c + 1/2,
// r + 1/2) 2R/T, sampled bilinearly and clamped to the edge outside; its rgb is added to the colour, its alpha is the
// opacity gain. Anti-aliased, the texture is prefiltered once per surfel (prepare: prefilter_texture): its deviation
// from its mean as the surfel shows it (weighted by the Gaussian falloff at the texel centres), per channel, times the
// footprint's gain at the texel grid's Nyquist frequency. Scatter slots: TEX_CHANNELS per texel, in the texture's own
// order (dL/d the texture the pixels saw).
constexpr int TEX_CHANNELS = 4;  // a texel: r, g, b, alpha
// The texture's half-width in sigmas (splatzoo.types.TEXTURE_RADIUS).
constexpr double TEXTURE_RADIUS = 3.0;

// The texture's footprint gain, anti-aliased: exp(-k_n^2 (b00 + b11) / 4), the mean over the u and v axes of a wave's
// gain at the texel grid's Nyquist frequency k_n = pi TS / (2R) (blur: Geom::blur). Once per surfel.
SZ_HD double texture_nyquist_sq(int TS) {
    const double kn = 3.14159265358979323846 * double(TS) / (2.0 * TEXTURE_RADIUS);
    return kn * kn;
}
template <class S>
SZ_HD S texture_gain(const S* blur, int TS) {
    return sz_exp(S(-0.25) * S(texture_nyquist_sq(TS)) * (blur[0] + blur[2]));
}

// The weight of texel j = (r, c) in the texture's mean: exp(-|centre|^2 / 2), normalised over the texels (what a
// surfel far smaller than the pixel shows of its texture, for the Gaussian falloff). norm: texel_weight_norm(TS).
SZ_HD double texel_centre(int TS, int i) { return TEXTURE_RADIUS * ((2.0 * i + 1.0) / TS - 1.0); }
SZ_HD double texel_weight_norm(int TS) {
    double sum = 0.0;
    for (int i = 0; i < TS; ++i) sum += exp(-0.5 * texel_centre(TS, i) * texel_centre(TS, i));
    return sum * sum;
}
SZ_HD double texel_weight(int TS, int j, double norm) {
    const double cu = texel_centre(TS, j % TS), cv = texel_centre(TS, j / TS);
    return exp(-0.5 * (cu * cu + cv * cv)) / norm;
}

// out = mean + gain (tex - mean), per channel, mean = sum_j texel_weight(j) tex_j: the texture an anti-aliased
// pixel sees.
template <class S>
SZ_HD void prefilter_texture(const S* blur, const S* tex, int TS, S* out) {
    const S gain = texture_gain(blur, TS);
    const int n = TS * TS;
    const double norm = texel_weight_norm(TS);
    for (int c = 0; c < TEX_CHANNELS; ++c) {
        S mean = S(0);
        for (int j = 0; j < n; ++j) mean += S(texel_weight(TS, j, norm)) * tex[TEX_CHANNELS * j + c];
        for (int j = 0; j < n; ++j) out[TEX_CHANNELS * j + c] = mean + gain * (tex[TEX_CHANNELS * j + c] - mean);
    }
}

// Where (u, v) falls on the texel grid: the first texel (its offset in the texture), the offsets to the next column
// and row (0 at the last, or for one texel), the bilinear fractions, and d(texel coordinate)/du, /dv (0 where the
// coordinate is clamped to the edge). A non-finite u or v reads texel 0 (such pairs are culled; no read goes out of
// the texture).
template <class S>
struct TexelSpot {
    int i00, du, dv;
    S fu, fv, gu, gv;
};
template <class S>
SZ_HD S texel_axis(int TS, S x, S& grad, int& i0, int& step) {
    const S scale = S(double(TS) / (2.0 * TEXTURE_RADIUS));
    const S t = radd(rmul(radd(x, S(TEXTURE_RADIUS)), scale), S(-0.5));  // rounded alike everywhere: see rmul
    const S top = S(TS - 1);
    const S c = smin(smax(t, S(0)), top);  // smax drops a NaN
    grad = t >= S(0) ? scale : S(0);  // torch.clamp passes the gradient for lo <= t <= hi
    grad = t <= top ? grad : S(0);
    const int last = TS >= 2 ? TS - 2 : 0;
    int i = int(c);
    i = i < last ? i : last;
    i0 = i;
    step = i + 1 < TS ? 1 : 0;
    return radd(c, -S(i));
}
template <class S>
SZ_HD TexelSpot<S> texel_spot(int TS, S u, S v) {
    TexelSpot<S> t;
    int iu, iv, su, sv;
    t.fu = texel_axis(TS, u, t.gu, iu, su);
    t.fv = texel_axis(TS, v, t.gv, iv, sv);
    t.i00 = TEX_CHANNELS * (iv * TS + iu);
    t.du = TEX_CHANNELS * su;
    t.dv = TEX_CHANNELS * TS * sv;
    return t;
}
// Channel c of the bilinear sample: lerp along u on the two rows, then along v. (Each operation rounded on its own:
// the alpha channel decides which pairs blend, in the forward and the backward alike; see rmul.)
template <class S>
SZ_HD S texel_lerp(const S* tex, const TexelSpot<S>& t, int c) {
    const S* p = tex + t.i00 + c;
    const S a = radd(p[0], rmul(t.fu, radd(p[t.du], -p[0])));
    const S b = radd(p[t.dv], rmul(t.fu, radd(p[t.dv + t.du], -p[t.dv])));
    return radd(a, rmul(t.fv, radd(b, -a)));
}

template <class S>
struct Texture {
    SZ_KIND_FIELD_MEMBERS(SZ_KIND_FIELDS_TEXTURE)  // texture [T,T,4], as given
    const S* tex;  // the texels the pixels read: texture, or anti-aliased its prefiltered copy (prepare); unread at T 0
    int TS;        // texels a side; 0: no texture

    // the pair's opacity gain (the texture's alpha), for the backward
    template <int KMAX>
    struct Cache {
        S gain;
    };

    SZ_HD static constexpr int dense_slots(int) { return 0; }
    SZ_HD static constexpr int scatter_slots(int, int T) { return TEX_CHANNELS * T * T; }
    SZ_HD static constexpr int prepared_width(int, int T, bool filtered) { return filtered ? TEX_CHANNELS * T * T : 0; }
    SZ_HD static constexpr int fold_values(int) { return 0; }
    SZ_HD static constexpr int fold_factors(int) { return 0; }
    SZ_HD bool has_gain() const { return TS > 0; }
    SZ_HD S gain(S u, S v) const { return texel_lerp(tex, texel_spot(TS, u, v), TEX_CHANNELS - 1); }

    template <class Args>
    SZ_HD void bind(const Args& a, int64_t i, const S* prepared) {
        bind_fields(a, i, a.K, a.TS);
        TS = a.TS;
        tex = TS == 0 ? nullptr : prepared ? prepared : texture;
    }
    SZ_HD void prepare(const S* blur, S* out) const { prefilter_texture(blur, texture, TS, out); }
    SZ_HD void fold(const Geom<S>&, S*, S*) {}
    SZ_HD void unfold(S*, int) const {}

    template <int KMAX>
    SZ_HD S add_colour(S u, S v, S rgb[3], const S*, Cache<KMAX>* c) const {
        if (TS == 0) return S(1);
        const TexelSpot<S> t = texel_spot(TS, u, v);
        rgb[0] += texel_lerp(tex, t, 0);
        rgb[1] += texel_lerp(tex, t, 1);
        rgb[2] += texel_lerp(tex, t, 2);
        const S g = texel_lerp(tex, t, 3);
        if (c) c->gain = g;
        return g;
    }

    // the texels, which differ from pixel to pixel, through acc.scatter; dL/dg = dL/d ln g / g (g > 0 wherever a pair
    // contributes)
    template <int KMAX, class Acc>
    SZ_HD void backward(S u, S v, const S v_col[3], S v_lngain, const S*, const Cache<KMAX>* c, Acc& acc, int,
                        int scatter, S& v_u, S& v_v) const {
        if (TS == 0) return;
        const TexelSpot<S> t = texel_spot(TS, u, v);
        const S v_gain = v_lngain / (c ? c->gain : texel_lerp(tex, t, TEX_CHANNELS - 1));
        const S w00 = (S(1) - t.fu) * (S(1) - t.fv), w01 = t.fu * (S(1) - t.fv);
        const S w10 = (S(1) - t.fu) * t.fv, w11 = t.fu * t.fv;
        const int o = scatter + t.i00;
        S d_fu = S(0), d_fv = S(0);
        for (int ch = 0; ch < TEX_CHANNELS; ++ch) {
            const S vc = ch < 3 ? v_col[ch] : v_gain;
            acc.scatter(o + ch, w00 * vc);
            acc.scatter(o + ch + t.du, w01 * vc);
            acc.scatter(o + ch + t.dv, w10 * vc);
            acc.scatter(o + ch + t.dv + t.du, w11 * vc);
            const S* p = tex + t.i00 + ch;
            const S a = p[0] + t.fu * (p[t.du] - p[0]);
            const S b = p[t.dv] + t.fu * (p[t.dv + t.du] - p[t.dv]);
            d_fu += vc * ((S(1) - t.fv) * (p[t.du] - p[0]) + t.fv * (p[t.dv + t.du] - p[t.dv]));
            d_fv += vc * (b - a);
        }
        v_u += d_fu * t.gu;
        v_v += d_fv * t.gv;
    }

    // prefiltered: t' = mean + gain (t - mean), mean = sum_j w_j t_j, gain = exp(-k_n^2 (b00 + b11) / 4), so
    // dL/dt_j = gain v_j + (1 - gain) w_j sum_i v_i and dL/dgain = sum_j v_j (t_j - mean)
    template <class R>
    SZ_HD void finalize(const R* Gs, int, int scatter, bool filtered, const double* b, double* v_blur,
                        const Grads& v) const {
        const int n = TS * TS;
        const R* gt = Gs + scatter;  // dL/d (the texture the pixels saw)
        if (n == 0) return;
        if (!filtered) {
            for (int j = 0; j < TEX_CHANNELS * n; ++j) v.v_texture[j] = S(gt[j]);
            return;
        }
        const double kn2 = texture_nyquist_sq(TS);
        const double gain = exp(-0.25 * kn2 * (b[0] + b[2]));
        const double norm = texel_weight_norm(TS);
        double v_gain = 0.0;
        for (int c = 0; c < TEX_CHANNELS; ++c) {
            double mean_t = 0.0, sum_v = 0.0;
            for (int j = 0; j < n; ++j) {
                mean_t += texel_weight(TS, j, norm) * double(texture[TEX_CHANNELS * j + c]);
                sum_v += double(gt[TEX_CHANNELS * j + c]);
            }
            for (int j = 0; j < n; ++j) {
                const double vj = double(gt[TEX_CHANNELS * j + c]);
                v_gain += vj * (double(texture[TEX_CHANNELS * j + c]) - mean_t);
                v.v_texture[TEX_CHANNELS * j + c] = S(gain * vj + (1.0 - gain) * texel_weight(TS, j, norm) * sum_v);
            }
        }
        v_blur[0] -= 0.25 * kn2 * gain * v_gain;
        v_blur[2] -= 0.25 * kn2 * gain * v_gain;
    }
};

// ---- the composition of the kinds ------------------------------------------------------------------------------
// One member per kind of the generated list (SZ_APPEARANCE_KINDS, table order); every method visits them in that
// order. A kind's blocks of the slot row: its dense block after the dense blocks of the kinds before it (the first
// at G_APPEARANCE), its scatter block after every dense block and the scatter blocks before it.
template <class S>
struct Appearance {
#define SZ_KIND_MEMBER(Kind, member, FIELDS) Kind<S> member;
    SZ_APPEARANCE_KINDS(SZ_KIND_MEMBER)
#undef SZ_KIND_MEMBER
    int K, T;  // the batch's sizes (wave count, texels a side): the slot row's layout

    struct Grads {
#define SZ_KIND_GRADS(Kind, member, FIELDS) typename Kind<S>::Grads member;
        SZ_APPEARANCE_KINDS(SZ_KIND_GRADS)
#undef SZ_KIND_GRADS
    };
    template <int KMAX>
    struct Cache {
#define SZ_KIND_CACHE(Kind, member, FIELDS) typename Kind<S>::template Cache<KMAX> member;
        SZ_APPEARANCE_KINDS(SZ_KIND_CACHE)
#undef SZ_KIND_CACHE
    };

    SZ_HD static constexpr int dense_slots(int K) {
#define SZ_KIND_DENSE(Kind, member, FIELDS) +Kind<S>::dense_slots(K)
        return 0 SZ_APPEARANCE_KINDS(SZ_KIND_DENSE);
#undef SZ_KIND_DENSE
    }
    SZ_HD static constexpr int scatter_slots(int K, int T) {
#define SZ_KIND_SCATTER(Kind, member, FIELDS) +Kind<S>::scatter_slots(K, T)
        return 0 SZ_APPEARANCE_KINDS(SZ_KIND_SCATTER);
#undef SZ_KIND_SCATTER
    }
    SZ_HD static constexpr int prepared_width(int K, int T, bool filtered) {
#define SZ_KIND_PREPARED(Kind, member, FIELDS) +Kind<S>::prepared_width(K, T, filtered)
        return 0 SZ_APPEARANCE_KINDS(SZ_KIND_PREPARED);
#undef SZ_KIND_PREPARED
    }
    SZ_HD static constexpr int fold_values(int K) {
#define SZ_KIND_FOLD_VALUES(Kind, member, FIELDS) +Kind<S>::fold_values(K)
        return 0 SZ_APPEARANCE_KINDS(SZ_KIND_FOLD_VALUES);
#undef SZ_KIND_FOLD_VALUES
    }
    SZ_HD static constexpr int fold_factors(int K) {
#define SZ_KIND_FOLD_FACTORS(Kind, member, FIELDS) +Kind<S>::fold_factors(K)
        return 0 SZ_APPEARANCE_KINDS(SZ_KIND_FOLD_FACTORS);
#undef SZ_KIND_FOLD_FACTORS
    }

    // Surfel i's appearance as its pairs see it (Args: SurfelArgs): its rows of the fields, the waves it uses, its
    // prepared row (anti-aliased: the prefiltered texture).
    template <class Args>
    SZ_HD static Appearance bind(const Args& a, int64_t i) {
        Appearance ap;
        ap.K = a.K;
        ap.T = a.TS;
        const bool filtered = a.st.pixel_filter > 0;
        const S* prepared = a.prepared ? a.prepared + int64_t(a.prepared_width) * i : nullptr;
#define SZ_KIND_BIND_KIND(Kind, member, FIELDS)                                                  \
    {                                                                                            \
        const int w = Kind<S>::prepared_width(a.K, a.TS, filtered);                              \
        ap.member.bind(a, i, w > 0 ? prepared : nullptr);                                        \
        if (prepared) prepared += w;                                                             \
    }
        SZ_APPEARANCE_KINDS(SZ_KIND_BIND_KIND)
#undef SZ_KIND_BIND_KIND
        return ap;
    }
    // Where the gradients of surfel i's fields go (Args: GradArgs; sizes: SurfelArgs).
    template <class G, class Args>
    SZ_HD static Grads bind_grads(const G& g, const Args& a, int64_t i) {
        Grads v;
#define SZ_KIND_BIND_GRADS(Kind, member, FIELDS) v.member = Kind<S>::bind_grads(g, i, a.K, a.TS);
        SZ_APPEARANCE_KINDS(SZ_KIND_BIND_GRADS)
#undef SZ_KIND_BIND_GRADS
        return v;
    }
    // The prepare step of visible surfel i (its Geom's blur done): every kind's set-up into its prepared row.
    template <class Args>
    SZ_HD static void prepare(const Args& a, const S* blur, int64_t i) {
        if (a.prepared == nullptr) return;
        const Appearance ap = bind(a, i);
        const bool filtered = a.st.pixel_filter > 0;
        S* out = a.prepared + int64_t(a.prepared_width) * i;
#define SZ_KIND_PREPARE(Kind, member, FIELDS)                                                    \
    {                                                                                            \
        const int w = Kind<S>::prepared_width(a.K, a.TS, filtered);                              \
        if (w > 0) ap.member.prepare(blur, out);                                                 \
        out += w;                                                                                \
    }
        SZ_APPEARANCE_KINDS(SZ_KIND_PREPARE)
#undef SZ_KIND_PREPARE
    }

    // Anti-aliased, per (surfel, tile) on the CPU: the kinds fold their footprint factors (g: the surfel's Geom, its
    // blur) into what the pixels read (values: fold_values(K) scalars, factors: fold_factors(K)); the pixels then pass
    // no blur. unfold (row: the pair's slot sums) afterwards.
    SZ_HD void fold(const Geom<S>& g, S* values, S* factors) {
#define SZ_KIND_FOLD(Kind, member, FIELDS)                                                       \
    member.fold(g, values, factors);                                                             \
    values += Kind<S>::fold_values(K);                                                           \
    factors += Kind<S>::fold_factors(K);
        SZ_APPEARANCE_KINDS(SZ_KIND_FOLD)
#undef SZ_KIND_FOLD
    }
    SZ_HD void unfold(S* row) const {
        int dense = G_APPEARANCE;
#define SZ_KIND_UNFOLD(Kind, member, FIELDS)                                                     \
    member.unfold(row, dense);                                                                   \
    dense += Kind<S>::dense_slots(K);
        SZ_APPEARANCE_KINDS(SZ_KIND_UNFOLD)
#undef SZ_KIND_UNFOLD
    }

    // Whether any kind has an opacity gain: the tile loops apply one (apply_opacity_gain) only then.
    SZ_HD bool has_gain() const {
        bool any = false;
#define SZ_KIND_HAS_GAIN(Kind, member, FIELDS) any = any || member.has_gain();
        SZ_APPEARANCE_KINDS(SZ_KIND_HAS_GAIN)
#undef SZ_KIND_HAS_GAIN
        return any;
    }
    // The opacity gain g(u, v): the product of the kinds' gains.
    SZ_HD S gain(S u, S v) const {
        S g = S(1);
#define SZ_KIND_GAIN(Kind, member, FIELDS) \
    if (member.has_gain()) g = g * member.gain(u, v);
        SZ_APPEARANCE_KINDS(SZ_KIND_GAIN)
#undef SZ_KIND_GAIN
        return g;
    }

    // rgb(u, v) before the clamp (pre) and after it (col); returns the opacity gain at (u, v). blur: Geom::blur when
    // anti-aliased and not folded, else nullptr. c: what the backward reuses, or nullptr.
    template <int KMAX = -1>
    SZ_HD S colour(S u, S v, S col[3], S pre[3], const S* blur = nullptr, Cache<KMAX>* c = nullptr) const {
        S rgb[3] = {S(-0.0), S(-0.0), S(-0.0)};  // -0 + x is x for every x: the first addition folds away
        S g = S(1);
#define SZ_KIND_COLOUR(Kind, member, FIELDS) \
    g = g * member.template add_colour<KMAX>(u, v, rgb, blur, c ? &c->member : nullptr);
        SZ_APPEARANCE_KINDS(SZ_KIND_COLOUR)
#undef SZ_KIND_COLOUR
        for (int i = 0; i < 3; ++i) {
            pre[i] = rgb[i];
            col[i] = smax(rgb[i], S(0));
        }
        return g;
    }

    // The colour's and the opacity gain's backward: v_col = dL/d pre (the clamp's gate applied), v_lngain = dL/d ln g.
    // Accumulates the kinds' slots (dense through acc, the same slots in the same order whatever the pair; scatter
    // through acc.scatter) and returns dL/d(u, v) in v_u, v_v (added). c: colour's cache of the same pair.
    template <int KMAX = -1, class Acc>
    SZ_HD void backward(S u, S v, const S v_col[3], S v_lngain, const S* blur, const Cache<KMAX>* c, Acc& acc,
                        S& v_u, S& v_v) const {
        int dense = G_APPEARANCE, scatter = G_APPEARANCE + dense_slots(K);
#define SZ_KIND_BACKWARD(Kind, member, FIELDS)                                                                     \
    member.template backward<KMAX>(u, v, v_col, v_lngain, blur, c ? &c->member : nullptr, acc, dense, scatter, v_u, \
                                   v_v);                                                                           \
    dense += Kind<S>::dense_slots(K);                                                                              \
    scatter += Kind<S>::scatter_slots(K, T);
        SZ_APPEARANCE_KINDS(SZ_KIND_BACKWARD)
#undef SZ_KIND_BACKWARD
    }

    // The appearance's blocks of a surfel's summed slot row -> the gradients of its fields (the appearance bound
    // afresh: the fields as given, not folded). Anti-aliased (b: the blur the pixels used), the kinds' footprint
    // factors add their gradients into v_blur (b00, b01, b11).
    template <class R>
    SZ_HD void finalize(const R* Gs, bool filtered, const double* b, double* v_blur, const Grads& v) const {
        int dense = G_APPEARANCE, scatter = G_APPEARANCE + dense_slots(K);
#define SZ_KIND_FINALIZE(Kind, member, FIELDS)                                 \
    member.finalize(Gs, dense, scatter, filtered, b, v_blur, v.member);        \
    dense += Kind<S>::dense_slots(K);                                          \
    scatter += Kind<S>::scatter_slots(K, T);
        SZ_APPEARANCE_KINDS(SZ_KIND_FINALIZE)
#undef SZ_KIND_FINALIZE
    }
};

// The width of a surfel's slot row (K waves, T texels a side): the geometry's slots and every kind's blocks.
SZ_HD constexpr int grad_width(int K, int T = 0) {
    return G_APPEARANCE + Appearance<float>::dense_slots(K) + Appearance<float>::scatter_slots(K, T);
}
// Its first slots, which every pair accumulates through acc (the geometry's and the kinds' dense blocks).
SZ_HD constexpr int dense_width(int K) { return G_APPEARANCE + Appearance<float>::dense_slots(K); }

// NDC depth of the distortion term, m(z) = f/(f-n) (1 - n/z), and dm/dz.
template <class S> SZ_HD S ndc_depth(const Settings& st, S z) {
    return S(st.far / (st.far - st.near)) * (S(1) - S(st.near) / z);
}
template <class S> SZ_HD S ndc_depth_grad(const Settings& st, S z) {
    return S(st.far / (st.far - st.near)) * S(st.near) / (z * z);
}

// ---- front-to-back compositing of one pixel ---------------------------------------------------------------------
template <class S>
struct PixelFwd {
    S T, rgb[3], D, N[3], A, M1, M2, dist, median;
    int last;  // 1 + list position (within the tile) of the last blended contribution; 0 if none
    int med;   // list position of the median-depth contribution; -1 if none
    bool done;
};

template <class S>
SZ_HD void pixel_init(PixelFwd<S>& p, bool done) {
    p.T = S(1);
    p.rgb[0] = p.rgb[1] = p.rgb[2] = S(0);
    p.D = S(0);
    p.N[0] = p.N[1] = p.N[2] = S(0);
    p.A = p.M1 = p.M2 = p.dist = p.median = S(0);
    p.last = 0;
    p.med = -1;
    p.done = done;
}

// Blend one valid contribution (alpha > 0) at tile-list position `pos`; col is the clamped colour, n the normal.
// Stops the pixel, without blending, when the contribution would bring T below t_min (reference: `kept`).
// IMAGE_ONLY: colour and transmittance only (a render to look at: no depth, normal, distortion or backward state).
template <bool IMAGE_ONLY = false, class S>
SZ_HD void blend_forward(const Settings& st, PixelFwd<S>& p, S alpha, S z, const S col[3], const S* n, int pos) {
    S Tn = p.T * (S(1) - alpha);
    if (Tn < S(st.t_min)) {
        p.done = true;
        return;
    }
    S w = alpha * p.T;
    p.rgb[0] += w * col[0];
    p.rgb[1] += w * col[1];
    p.rgb[2] += w * col[2];
    if constexpr (IMAGE_ONLY) {
        p.T = Tn;
        return;
    }
    p.D += w * z;
    p.N[0] += w * n[0];
    p.N[1] += w * n[1];
    p.N[2] += w * n[2];
    S m = ndc_depth(st, z);
    // distortion sum_i w_i sum_{j<i} w_j (m_i - m_j)^2 from exclusive running sums, as the reference does
    p.dist += w * (m * m * p.A + p.M2 - S(2) * m * p.M1);
    p.A += w;
    p.M1 += w * m;
    p.M2 += w * m * m;
    if (p.T > S(0.5)) {  // median depth: the last contribution that starts while T > 0.5
        p.median = z;
        p.med = pos;
    }
    p.T = Tn;
    p.last = pos + 1;
}

// ---- backward ---------------------------------------------------------------------------------------------------
// Per-pixel state for the back-to-front pass. From the forward: T_final, the totals A = sum w, M1 = sum w m,
// M2 = sum w m^2, last, med. From the cotangents: v_rgb, v_D (of sum w z), v_Tf (of T_final), v_n, v_dist, v_med.
template <class S>
struct PixelBwd {
    S T;       // transmittance after the contribution being processed (starts at T_final)
    S suffix;  // sum over later contributions of w_j f_j
    S Tfinal, A, M1, M2;
    S v_rgb[3], v_D, v_Tf, v_n[3], v_dist, v_med;
    int last, med;
};

// Cotangents of the six outputs -> PixelBwd. depth = D / (1 - T_final) where 1 - T_final > 0, else 0.
template <class S>
SZ_HD void pixel_bwd_init(PixelBwd<S>& p, S Tfinal, const S* tot, int last, int med, S depth_out, const S* v_rgb,
                          S v_alpha, S v_depth, S v_median, const S* v_normal, S v_dist) {
    p.T = Tfinal;
    p.suffix = S(0);
    p.Tfinal = Tfinal;
    p.A = tot[0]; p.M1 = tot[1]; p.M2 = tot[2];
    S acc = S(1) - Tfinal;
    bool pos = acc > S(0);
    p.v_D = pos ? v_depth / acc : S(0);
    S v_acc = v_alpha - (pos ? v_depth * depth_out / acc : S(0));
    p.v_Tf = -v_acc;
    for (int i = 0; i < 3; ++i) { p.v_rgb[i] = v_rgb[i]; p.v_n[i] = v_normal[i]; }
    p.v_dist = v_dist;
    p.v_med = v_median;
    p.last = last;
    p.med = med;
}

// d(alpha, z, u, v) -> surfel slots (opacity, centre, centre depth, and c = h_x x h_y through u, v).
// Every slot is accumulated on every call (zero where it does not apply), in a fixed order, so a caller may sum
// each slot across threads (the CUDA warp reduction) with every thread taking part.
template <class F, class S, class Acc>
SZ_HD void geom_backward(const Settings& st, const Geom<S>& g, const PairEval<S>& e, S v_alpha, S v_z, S v_u, S v_v,
                         Acc& acc) {
    const bool clamped = e.raw > S(st.alpha_max);  // torch.clamp passes the gradient only where input <= max
    S d_rho, d_s;
    F::dlog(e.rho, g.s, d_rho, d_s);
    const S v_lnf = clamped ? S(0) : v_alpha * e.raw;  // dL/d ln f
    const S v_rho = v_lnf * d_rho;
    acc(G_O, clamped ? S(0) : v_alpha * e.ex);
    acc(G_S, v_lnf * d_s);
    // the ray-splat hit won (use3): rho = u^2 + v^2 at the hit, whose depth is m3 . (u, v, 1)
    const bool hit = e.use3;
    v_u += S(2) * e.u * v_rho + v_z * g.m3[0];
    v_v += S(2) * e.v * v_rho + v_z * g.m3[1];
    acc(G_M3 + 0, hit ? v_z * e.u : S(0));
    acc(G_M3 + 1, hit ? v_z * e.v : S(0));
    acc(G_M3 + 2, hit ? v_z : S(0));
    const S inv = S(1) / (hit ? e.c2 : S(1));
    S v_c[3] = {v_u * inv, v_v * inv, -(v_u * e.u + v_v * e.v) * inv};
    for (int i = 0; i < 3; ++i) v_c[i] = hit ? v_c[i] : S(0);
    for (int i = 0; i < 3; ++i) {
        acc(G_C + i, v_c[i]);
        acc(G_CX + i, e.dx * v_c[i]);
        acc(G_CY + i, e.dy * v_c[i]);
    }
    // otherwise the filter won: rho = F |d|^2 with d = pixel - centre, and the surfel is seen at its centre depth
    acc(G_ZC, hit ? S(0) : v_z);
    acc(G_CENTER + 0, hit ? S(0) : S(-2 * st.filter_inv_sq) * v_rho * e.dx);
    acc(G_CENTER + 1, hit ? S(0) : S(-2 * st.filter_inv_sq) * v_rho * e.dy);
}

// geom_backward of an anti-aliased pair (eval_pair_filtered): d(alpha, z, colour centre P x) -> the slots, through
// P = (I + S)^-1, det(I + S), S = f J J^T, J = d(u, v)/d(pixel) and the hit x = (c0, c1) / c2. P's off-diagonal is
// one parameter (it appears twice in the symmetric matrix).
template <class F, class S, class Acc>
SZ_HD void geom_backward_filtered(const Settings& st, const Geom<S>& g, const PairEval<S>& e, S v_alpha, S v_z,
                                  S v_mu, S v_mv, Acc& acc) {
    const bool clamped = e.raw > S(st.alpha_max);
    const S v_raw = clamped ? S(0) : v_alpha;
    acc(G_O, v_raw * e.ex);
    S d_q, d_s;
    F::dlog(e.rho, g.s, d_q, d_s);
    const S v_q = v_raw * e.raw * d_q;  // raw = o det^-1/2 f(q)
    acc(G_S, v_raw * e.raw * d_s);
    // z = m3 . (P x, 1)
    v_mu += v_z * g.m3[0];
    v_mv += v_z * g.m3[1];
    acc(G_M3 + 0, v_z * e.u);
    acc(G_M3 + 1, v_z * e.v);
    acc(G_M3 + 2, v_z);
    const S u = e.xu, v = e.xv;
    // colour centre = P x, q = x^T P x
    const S v_p00 = v_mu * u + v_q * u * u;
    const S v_p01 = v_mu * v + v_mv * u + S(2) * v_q * u * v;
    const S v_p11 = v_mv * v + v_q * v * v;
    S v_u = e.p00 * v_mu + e.p01 * v_mv + S(2) * v_q * (e.p00 * u + e.p01 * v);
    S v_v = e.p01 * v_mu + e.p11 * v_mv + S(2) * v_q * (e.p01 * u + e.p11 * v);
    // P = [[1 + s11, -s01], [-s01, 1 + s00]] / det, det = (1 + s00)(1 + s11) - s01^2, gain = det^-1/2
    const S f = S(st.pixel_filter);
    const S s00 = f * (e.j00 * e.j00 + e.j01 * e.j01);
    const S s01 = f * (e.j00 * e.j10 + e.j01 * e.j11);
    const S s11 = f * (e.j10 * e.j10 + e.j11 * e.j11);
    const S idet = e.idet;
    const S v_det = S(-0.5) * v_raw * e.raw * idet -
                    (v_p00 * (S(1) + s11) - v_p01 * s01 + v_p11 * (S(1) + s00)) * idet * idet;
    const S v_s00 = v_p11 * idet + v_det * (S(1) + s11);
    const S v_s11 = v_p00 * idet + v_det * (S(1) + s00);
    const S v_s01 = -v_p01 * idet - S(2) * v_det * s01;
    // S = f J J^T
    const S v_j00 = f * (S(2) * e.j00 * v_s00 + e.j10 * v_s01);
    const S v_j01 = f * (S(2) * e.j01 * v_s00 + e.j11 * v_s01);
    const S v_j10 = f * (S(2) * e.j10 * v_s11 + e.j00 * v_s01);
    const S v_j11 = f * (S(2) * e.j11 * v_s11 + e.j01 * v_s01);
    // J = [[A0 - u A2, B0 - u B2], [A1 - v A2, B1 - v B2]] / c2
    const S inv = e.inv;
    acc(G_A + 0, v_j00 * inv);
    acc(G_A + 1, v_j10 * inv);
    acc(G_A + 2, -(u * v_j00 + v * v_j10) * inv);
    acc(G_B + 0, v_j01 * inv);
    acc(G_B + 1, v_j11 * inv);
    acc(G_B + 2, -(u * v_j01 + v * v_j11) * inv);
    v_u -= (g.A[2] * v_j00 + g.B[2] * v_j01) * inv;
    v_v -= (g.A[2] * v_j10 + g.B[2] * v_j11) * inv;
    const S v_c2 = -(e.j00 * v_j00 + e.j01 * v_j01 + e.j10 * v_j10 + e.j11 * v_j11) * inv;
    // x = (c0, c1) / c2
    const S v_c[3] = {v_u * inv, v_v * inv, -(v_u * u + v_v * v) * inv + v_c2};
    for (int i = 0; i < 3; ++i) {
        acc(G_C + i, v_c[i]);
        acc(G_CX + i, e.dx * v_c[i]);
        acc(G_CY + i, e.dy * v_c[i]);
    }
    acc(G_ZC, S(0));  // no screen filter: the same slots as geom_backward, for the warp sums
    acc(G_CENTER + 0, S(0));
    acc(G_CENTER + 1, S(0));
}

// The cotangents one contribution hands to the pair's geometry: of its alpha, its depth and the point (u, v) its
// colour is taken at.
template <class S>
struct PairCotangents {
    S alpha, z, u, v;
};

// One contribution, back to front, up to its geometry: updates the pixel state, accumulates the normal and the
// appearance slots and returns what geom_backward(_filtered) takes from here.
// Contributions must be visited in reverse blending order, each exactly once. e: the pair (alpha > 0 and
// pos < last; with an opacity gain, e.raw is o f g as apply_opacity_gain left it); ap: this surfel's appearance; n its
// normal; blur: Geom::blur when anti-aliased, else nullptr. Calls acc for the same slots in the same order whatever
// the pair (and acc.scatter for the kinds' scatter slots). A caller that folded the appearance (Appearance::fold)
// passes no blur and unfolds the summed slots afterwards (Appearance::unfold): every slot comes out the same.
template <int KMAX = -1, class S, class Acc>
SZ_HD PairCotangents<S> blend_backward_colour(const Settings& st, PixelBwd<S>& p, const PairEval<S>& e, const S* n,
                                              const Appearance<S>& ap, int pos, Acc& acc, const S* blur) {
    S a = e.alpha;
    S oma = S(1) - a;
    S Ti = p.T / oma;  // transmittance before this contribution
    S w = a * Ti;
    S col[3], pre[3];
    // what the colour's backward reuses of its forward (each wave's sin and cos, ...)
    typename Appearance<S>::template Cache<KMAX> cache;
    ap.template colour<KMAX>(e.u, e.v, col, pre, blur, &cache);
    S m = ndc_depth(st, e.z);
    // dL/dw of this contribution (the distortion is quadratic in w: its derivative uses the pixel totals)
    S f = p.v_rgb[0] * col[0] + p.v_rgb[1] * col[1] + p.v_rgb[2] * col[2] + p.v_D * e.z +
          p.v_n[0] * n[0] + p.v_n[1] * n[1] + p.v_n[2] * n[2] +
          p.v_dist * (m * m * p.A - S(2) * m * p.M1 + p.M2);
    // w_j (j > i) carries a factor (1 - alpha_i), and so does T_final
    S v_alpha = Ti * f - (p.suffix + p.v_Tf * p.Tfinal) / oma;
    p.suffix += w * f;
    p.T = Ti;
    S v_z = w * p.v_D + p.v_dist * S(2) * w * (m * p.A - p.M1) * ndc_depth_grad(st, e.z);
    if (pos == p.med) v_z += p.v_med;
    acc(G_NORMAL + 0, w * p.v_n[0]);
    acc(G_NORMAL + 1, w * p.v_n[1]);
    acc(G_NORMAL + 2, w * p.v_n[2]);
    // colour: the clamp at 0 passes the gradient where the value is >= 0 (torch.clamp)
    S v_col[3];
    for (int i = 0; i < 3; ++i) v_col[i] = pre[i] >= S(0) ? w * p.v_rgb[i] : S(0);
    // the opacity gain: alpha = min(o f g, alpha_max), so dL/d ln g = dL/d alpha o f g = dL/d alpha raw below the
    // clamp
    S v_lngain = S(0);
    if (ap.has_gain()) v_lngain = e.raw > S(st.alpha_max) ? S(0) : v_alpha * e.raw;
    S v_u = S(0), v_v = S(0);
    ap.template backward<KMAX>(e.u, e.v, v_col, v_lngain, blur, &cache, acc, v_u, v_v);
    return {v_alpha, v_z, v_u, v_v};
}

// One contribution, back to front, whole: blend_backward_colour, then the pair's geometry. Calls acc for the same
// slots in the same order whatever the pair (see geom_backward).
template <int KMAX = -1, class S, class Acc>
SZ_HD void blend_backward(const Settings& st, PixelBwd<S>& p, const Geom<S>& g, const PairEval<S>& e, const S* n,
                          const Appearance<S>& ap, int pos, Acc& acc) {
    const bool filtered = st.pixel_filter > 0;
    const PairCotangents<S> v = blend_backward_colour<KMAX>(st, p, e, n, ap, pos, acc, filtered ? g.blur : nullptr);
    if (filtered)
        with_falloff(g.s, [&](auto falloff) SZ_INLINE_LAMBDA {
            geom_backward_filtered<decltype(falloff)>(st, g, e, v.alpha, v.z, v.u, v.v, acc);
        });
    else  // where the filter wins u = v = 0 are constants (reference: torch.where), so v_u, v_v are dropped there
        with_falloff(g.s, [&](auto falloff) SZ_INLINE_LAMBDA {
            geom_backward<decltype(falloff)>(st, g, e, v.alpha, v.z, v.u, v.v, acc);
        });
}

// Where the gradients of one surfel's inputs go: the projection's outputs (T, centre, centre depth, normal), the
// opacity fields and the appearance's fields.
template <class S>
struct SurfelGrads {
    S *v_T, *v_center, *v_depth, *v_normal, *v_opacities, *v_falloff;
    typename Appearance<S>::Grads appearance;
};

// A surfel's summed slot row -> gradients of the op inputs. Computed in double: it runs once per surfel.
// A = m2 x m3, B = m3 x m1, C = m1 x m2 with c(x, y) = x A + y B + C, so dL/dA = sum x dL/dc = G_CX + cx G_C, etc.
// Anti-aliased, the kinds' blur goes through centre_footprint, whose cz = C2 + cx A2 + cy B2 also depends on the
// centre. ap: the surfel's appearance, bound afresh (Appearance::finalize).
template <class S, class R>
SZ_HD void finalize_grads(const Settings& st, const S* T9, const S* center, const Appearance<S>& ap, const R* Gs,
                          const SurfelGrads<S>& v) {
    double m1[3], m2[3], m3[3], v_A[3], v_B[3], v_C[3];
    double cx = double(center[0]), cy = double(center[1]);
    // the slots hold gradients of the scaled A, B, C the pixels saw (prepare_geom)
    const double scale = plane_coeffs(T9, center).scale;
    for (int i = 0; i < 3; ++i) {
        m1[i] = double(T9[i]);
        m2[i] = double(T9[3 + i]);
        m3[i] = double(T9[6 + i]);
        v_C[i] = double(Gs[G_C + i]) * scale;
        v_A[i] = (double(Gs[G_CX + i]) + double(Gs[G_A + i])) * scale + cx * v_C[i];
        v_B[i] = (double(Gs[G_CY + i]) + double(Gs[G_B + i])) * scale + cy * v_C[i];
    }
    double v_cx = double(Gs[G_CENTER]), v_cy = double(Gs[G_CENTER + 1]);
    const bool filtered = st.pixel_filter > 0;
    CentreFootprint fp{};
    if (filtered) fp = centre_footprint(st, T9, center);
    const double b[3] = {double(S(fp.blur[0])), double(S(fp.blur[1])), double(S(fp.blur[2]))};
    double v_blur[3] = {0.0, 0.0, 0.0};
    ap.finalize(Gs, filtered, b, v_blur, v.appearance);
    if (filtered) {
        const double v_cz = centre_blur_backward(st, fp, v_blur, v_A, v_B);
        v_C[2] += v_cz;
        v_A[2] += cx * v_cz;
        v_B[2] += cy * v_cz;
        v_cx += fp.A[2] * v_cz;
        v_cy += fp.B[2] * v_cz;
    }
    // d(a x b): v_su_tu = b x g, v_sv_tv = g x a
    auto cross = [](const double* a, const double* b, double* out, double sign) {
        out[0] += sign * (a[1] * b[2] - a[2] * b[1]);
        out[1] += sign * (a[2] * b[0] - a[0] * b[2]);
        out[2] += sign * (a[0] * b[1] - a[1] * b[0]);
    };
    double v_m1[3] = {0, 0, 0}, v_m2[3] = {0, 0, 0}, v_m3[3] = {0, 0, 0};
    cross(m3, v_A, v_m2, 1.0);  // A = m2 x m3
    cross(v_A, m2, v_m3, 1.0);
    cross(m1, v_B, v_m3, 1.0);  // B = m3 x m1
    cross(v_B, m3, v_m1, 1.0);
    cross(m2, v_C, v_m1, 1.0);  // C = m1 x m2
    cross(v_C, m1, v_m2, 1.0);
    for (int i = 0; i < 3; ++i) {
        v.v_T[i] = S(v_m1[i]);
        v.v_T[3 + i] = S(v_m2[i]);
        v.v_T[6 + i] = S(v_m3[i] + double(Gs[G_M3 + i]));
        v.v_normal[i] = S(Gs[G_NORMAL + i]);
    }
    v.v_center[0] = S(v_cx);
    v.v_center[1] = S(v_cy);
    v.v_depth[0] = S(Gs[G_ZC]);
    v.v_opacities[0] = S(Gs[G_O]);
    v.v_falloff[0] = S(Gs[G_S]);
}

// Pixel range [x0, x1] x [y0, y1] (inclusive, clamped to the image; empty if x0 > x1 or y0 > y1) of the pixel
// centres i + 0.5 inside a screen box (xmin, ymin, xmax, ymax). The boxes are exact (common.screen_boxes).
template <class S>
SZ_HD void box_pixels(const S* box, int W, int H, int* out) {
    double lim = 1e9;  // keeps the int conversion defined for huge boxes
    double bx0 = smin(smax(double(box[0]), -lim), lim), by0 = smin(smax(double(box[1]), -lim), lim);
    double bx1 = smin(smax(double(box[2]), -lim), lim), by1 = smin(smax(double(box[3]), -lim), lim);
    int x0 = int(ceil(bx0 - 0.5)), y0 = int(ceil(by0 - 0.5));
    int x1 = int(floor(bx1 - 0.5)), y1 = int(floor(by1 - 0.5));
    out[0] = smax(x0, 0);
    out[1] = smin(x1, W - 1);
    out[2] = smax(y0, 0);
    out[3] = smin(y1, H - 1);
}

// The tiles a pixel range (box_pixels' output) touches, inclusive: the one rule every binning step uses.
struct TileRange {
    int x0, x1, y0, y1;
    SZ_HD int64_t count() const { return x0 <= x1 && y0 <= y1 ? int64_t(x1 - x0 + 1) * (y1 - y0 + 1) : 0; }
};
SZ_HD TileRange tile_range(const int* pixels) {
    if (pixels[0] > pixels[1] || pixels[2] > pixels[3]) return {0, -1, 0, -1};
    return {pixels[0] / TILE, pixels[1] / TILE, pixels[2] / TILE, pixels[3] / TILE};
}

}  // namespace sz
