// Generated from the Surfels field table (splatzoo/types.py) by `python -m splatzoo.rasterizers.fields`: do
// not edit. Every per-surfel field, in table order (the order render() takes them in); the bindings (ext.cpp) derive
// their checks, arguments and gradient buffers from it, and the tile loops' argument structs (rasterize.h) their
// per-pair pointers.
#pragma once

namespace sz {

enum class Role { geometry, opacity, appearance };
constexpr int SZ_K = -1;  // a dimension equal to the batch's wave count K
constexpr int SZ_T = -2;  // a dimension equal to the batch's texture size T (texels a side)

struct SurfelFieldInfo {
    const char* name;
    Role role;
    int rank;  // trailing dimensions after N
    int dims[3];  // SZ_K: K, SZ_T: T
};

constexpr int NUM_SURFEL_FIELDS = 10;
constexpr SurfelFieldInfo SURFEL_FIELD_INFO[NUM_SURFEL_FIELDS] = {
    {"means", Role::geometry, 1, {3, 0, 0}},  // centre in world space
    {"quats", Role::geometry, 1, {4, 0, 0}},  // rotation (w, x, y, z), need not be normalised
    {"scales", Role::geometry, 1, {2, 0, 0}},  // linear sigma along u, v
    {"opacities", Role::opacity, 0, {0, 0, 0}},  // peak opacity
    {"base_color", Role::appearance, 1, {3, 0, 0}},  // view-evaluated colour c0
    {"wave_vectors", Role::appearance, 2, {SZ_K, 2, 0}},  // k_k, radians per sigma
    {"wave_phases", Role::appearance, 1, {SZ_K, 0, 0}},  // phi_k, radians
    {"wave_amplitudes", Role::appearance, 2, {SZ_K, 3, 0}},  // a_k, colour per wave
    {"falloff", Role::opacity, 0, {0, 0, 0}},  // falloff exponent s: 0 the Gaussian exp(-rho/2), else the Beta kernel (1 - s rho/2)^(1/s)
    {"texture", Role::appearance, 3, {SZ_T, SZ_T, 4}},  // RGBA texels over (u, v) in [-TEXTURE_RADIUS, TEXTURE_RADIUS]^2 sigmas: rgb added to the colour, alpha times the opacity
};

}  // namespace sz

// X(name) for every field, in table order
#define SZ_SURFEL_FIELDS(X) X(means) X(quats) X(scales) X(opacities) X(base_color) X(wave_vectors) X(wave_phases) X(wave_amplitudes) X(falloff) X(texture)
// X(name) for the fields the tile loops read per (surfel, pixel) pair (every role but geometry)
#define SZ_PAIR_FIELDS(X) X(opacities) X(base_color) X(wave_vectors) X(wave_phases) X(wave_amplitudes) X(falloff) X(texture)
// X(name, row) for the fields of each appearance kind, in table order; row: the field's scalars per surfel, in terms
// of the batch's sizes K and T (names the expansion site defines). Each kind's struct (surfel_math.h) declares its
// field pointers and gradient pointers from its list.
#define SZ_KIND_FIELDS_WAVE_BANK(X) X(base_color, 3) X(wave_vectors, K * 2) X(wave_phases, K) X(wave_amplitudes, K * 3)
#define SZ_KIND_FIELDS_TEXTURE(X) X(texture, T * T * 4)
#define SZ_APPEARANCE_KINDS(X) X(WaveBank, wave_bank, SZ_KIND_FIELDS_WAVE_BANK) X(Texture, texture, SZ_KIND_FIELDS_TEXTURE)
