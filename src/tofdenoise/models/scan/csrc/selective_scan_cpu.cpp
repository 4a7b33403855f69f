// Selective scan (Mamba S6 recurrence) on the CPU: forward and recomputing backward, float32.
//
//   delta_t = softplus(delta_raw_t + bias)            (bias / softplus optional)
//   h_t     = exp(delta_t A) h_{t-1} + delta_t u_t B_t
//   y_t     = C_t . h_t + D u_t
//
// Layout (channels last, what the Python side hands over without copies in SS2D):
//   u      (batch, L, Du)        Du = G * Dg (plain scan) or Dg (SS2D: the 4 directions read the same x)
//   delta  (batch, L, G * Dg)    raw steps, one channel per (group, channel-in-group)
//   A      (G * Dg, N)           D, bias (G * Dg)
//   B, C   (batch, L, G, N)      any strides (SS2D passes slices of the x_proj output)
//   y      (batch, L, Du)        SS2D: the 4 directions are summed (cross_merge) into one output
// Position: the scan step l of group g reads spatial position p = pos(g, l). Plain scan: p = l. SS2D
// (G = 4 directions over an H x W image, L = H W): row-major, column-major, and both reversed.
//
// Work split: one task per (batch, range of blocks of W = 16 channels-in-group). A task walks every group in turn,
// so the SS2D sum over directions (y, du) needs no atomics. The forward walks its blocks together chunk by chunk,
// so that a chunk's B and C rows (shared by the group's channels) come from memory once for all of them (a frame's
// first DVSS level: 1.09x at 2 threads, docs/benchmarks.md); its ranges are as few as keep every thread busy. The 16
// channels are the vector lanes; the N states of the block (N x 16 floats) stay in registers and L1. exp(delta A) is one vectorisable range reduction + polynomial. Positions are walked in chunks of T: a pass
// over a chunk's steps (softplus, inputs, prefetches) precedes the recurrence over them.
// The forward saves the state entering every chunk (unless chunk <= 0: inference); the backward walks chunks in
// reverse, recomputes the chunk's states and decays from that checkpoint into a small buffer, and runs the adjoint
// recursion g_t = C_t dy_t + a_{t+1} g_{t+1}. dB, dC (shared by a group's channels) are reduced over the lanes
// and summed over a task's blocks in place (one partial per task of a batch element, summed by the caller);
// dA, dD, dbias per batch element (summed by the caller).
#include <torch/extension.h>
#include <ATen/Parallel.h>
#include <immintrin.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>

namespace {

constexpr int W = 16;     // lanes: channels per task
constexpr int NMAX = 64;  // largest d_state
constexpr int RMAX = 64;  // largest dt_rank of the fused dt projection (ss2d_fwd_lowrank)
constexpr int64_t ADJ_AHEAD = 4;  // steps ahead for the adjoint pass's prefetches
constexpr int64_t INFERENCE_CHUNK = 64;  // positions per step pass when no checkpoints are kept

// 16-float vectors (GCC / Clang vector extensions: one AVX-512 register, two AVX2 registers, ...). Values
// that live across the state loop are vf locals, so that the compiler keeps them in registers.
typedef float vf __attribute__((vector_size(64)));
typedef int32_t vi __attribute__((vector_size(64)));

inline vf splat(float x) { return vf{} + x; }
inline vf loadv(const float* p) {
    vf v;
    std::memcpy(&v, p, sizeof(v));
    return v;
}
inline void storev(float* p, vf v) { std::memcpy(p, &v, sizeof(v)); }
// lanes [0, nw) from p, the rest 0
inline vf load_lanes(const float* p, int nw) {
    if (nw == W) return loadv(p);
    alignas(64) float tmp[W] = {};
    std::memcpy(tmp, p, sizeof(float) * nw);
    return loadv(tmp);
}
inline void store_lanes(float* p, vf v, int nw) {
    if (nw == W) {
        storev(p, v);
    } else {
        alignas(64) float tmp[W];
        storev(tmp, v);
        std::memcpy(p, tmp, sizeof(float) * nw);
    }
}
// lanes at element stride `stride` (a channel axis that is not innermost: gathered / scattered)
inline vf load_lanes(const float* p, int64_t stride, int nw) {
    if (stride == 1) return load_lanes(p, nw);
    alignas(64) float tmp[W] = {};
    for (int j = 0; j < nw; ++j) tmp[j] = p[j * stride];
    return loadv(tmp);
}
inline void store_lanes(float* p, int64_t stride, vf v, int nw) {
    if (stride == 1) return store_lanes(p, v, nw);
    alignas(64) float tmp[W];
    storev(tmp, v);
    for (int j = 0; j < nw; ++j) p[j * stride] = tmp[j];
}
// W ones: load_lanes(zero_tail_mask(), nw) is 1 in lanes [0, nw) and 0 after
static_assert(W == 16, "zero_tail_mask spells out W ones");
inline const float* zero_tail_mask() {
    alignas(64) static const float ones[W] = {1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1};
    return ones;
}
// Element-wise choices as vector conditionals (one compare and one blend; spelled as and/andnot/or of a mask
// they cost 3 instructions each). max / min: one instruction with AVX-512 (GCC does not always turn the
// conditional into vmaxps / vminps inside the unrolled state loop; the exp's clamp takes two per state update).
inline vf select(vi mask, vf a, vf b) { return mask ? a : b; }
#if defined(__AVX512F__)
inline vf vmax(vf a, vf b) { return (vf)_mm512_max_ps((__m512)a, (__m512)b); }
inline vf vmin(vf a, vf b) { return (vf)_mm512_min_ps((__m512)a, (__m512)b); }
#else
inline vf vmax(vf a, vf b) { return a > b ? a : b; }
inline vf vmin(vf a, vf b) { return a < b ? a : b; }
#endif

// exp(x): x = n ln2 + r, |r| <= ln2 / 2; exp(r) = 1 + r + r^2 q(r) with q of degree 3 fitted for the least
// largest relative error on that interval (a Lawson-weighted least-squares fit, coefficients rounded to float;
// 1.6e-7 relative in float arithmetic, less than the degree-6 Taylor polynomial it replaces, with one multiply-add
// fewer). n = round(x / ln2) by the 1.5 * 2^23 trick (needs no reassociation of float sums: the build does not
// use -fassociative-math); t = x / ln2 + 1.5 * 2^23 then holds 0x4B400000 + n in its bits, so t's bits shifted
// left by 23 are n in the exponent field, and adding them to exp(r)'s bits multiplies it by 2^n (one shift and
// one integer add, no float conversion and no multiply). Clamped to [-87, 88] (exp(-87) ~ 1.6e-38 stands for 0),
// where exp(r) 2^n stays a normal float.
inline vf exp_v(vf x) {
    x = vmin(vmax(x, splat(-87.0f)), splat(88.0f));
    const vf magic = splat(12582912.0f);
    const vf t = x * 1.44269504088896341f + magic;
    const vf n = t - magic;
    vf r = x - n * 0.693359375f;
    r = r + n * 2.12194440e-4f;
    vf p = splat(0.00831252709031105f);
    p = p * r + 0.04189011827111244f;
    p = p * r + 0.16667114198207855f;
    p = p * r + 0.499992311000824f;
    p = p * r + 1.0f;
    p = p * r + 1.0f;
#if defined(__AVX512F__)
    return (vf)_mm512_scalef_ps((__m512)p, (__m512)n);  // p 2^n in one instruction
#else
    return (vf)((vi)p + ((vi)t << 23));
#endif
}

// 2^x for the decays exp(delta A), forward and backward (x = delta * A log2(e) <= 0, A log2(e) folded into the
// block's constants; on AVX-512 builds, the training route's too since 2026-11-28): f =
// x - floor(x) in [0, 1) in one instruction (vreduceps, round down), 2^f by a degree-5 polynomial fitted on [0, 1]
// with p(0) = 1 (so that 2^n is exact: x = -126 gives the smallest normal float) for the least largest relative error
// (Lawson-weighted least squares, coefficients rounded to float: 8.2e-8 in exact arithmetic, 1.8e-7 in float, as
// exp_v), and 2^f 2^floor(x) by scalef, which floors its exponent operand itself.
// Seven instructions, where a clamp, a rounding and a subtraction before the same polynomial took nine. No clamp: x
// below -150 gives 0 (scalef underflows; -inf gives 0, no NaN); the denormal results of x in (-150, -126] are
// flushed to 0 by the caller (DenormalFlush: the recurrence then never meets a denormal operand). AVX-512 (DQ for
// vreduceps) only; elsewhere exp_v(x ln 2).
constexpr bool HAVE_EXP2_FAST =
#if defined(__AVX512F__) && defined(__AVX512DQ__)
    true;
#else
    false;
#endif
inline vf exp2_v(vf x) {
#if defined(__AVX512F__) && defined(__AVX512DQ__)
    const vf f = (vf)_mm512_reduce_ps((__m512)x, _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC);  // x - floor(x)
    vf p = splat(0.0018671308644115925f);
    p = p * f + 0.009017028845846653f;
    p = p * f + 0.05579991266131401f;
    p = p * f + 0.24016444385051727f;
    p = p * f + 0.6931512951850891f;
    p = p * f + 1.0f;
    return (vf)_mm512_scalef_ps((__m512)p, (__m512)x);  // p 2^floor(x)
#else
    return exp_v(x * 0.6931471805599453f);
#endif
}

// Flush-to-zero and denormals-are-zero (MXCSR) on this thread for a scope, restored after: exp2_v leaves its denormal
// results to it.
struct DenormalFlush {
    unsigned int saved;
    DenormalFlush() : saved(_mm_getcsr()) { _mm_setcsr(saved | 0x8040u); }
    ~DenormalFlush() { _mm_setcsr(saved); }
    DenormalFlush(const DenormalFlush&) = delete;
    DenormalFlush& operator=(const DenormalFlush&) = delete;
};

// The decays exp(delta A) of the forward and the backward: exp2_v of delta A log2(e) where the build has it (denormal
// results flushed: run the tasks through decay_scope), exp_v of delta A elsewhere. One setting for both directions,
// so that the backward recomputes the forward's decays bit for bit.
constexpr bool EXP2 = HAVE_EXP2_FAST;
// f() under the denormal flush that exp2_v needs (nothing to set where the decays take exp_v)
template <class F>
void decay_scope(F&& f) {
    if constexpr (EXP2) {
        const DenormalFlush flush;
        f();
    } else {
        f();
    }
}

// 2 atanh(s) = log((1 + s) / (1 - s)) for s in (0, 1/3], by its odd series to s^13 (truncation < 2e-8 relative).
inline vf two_atanh_v(vf s) {
    const vf s2 = s * s;
    vf p = splat(1.0f / 13.0f);
    p = p * s2 + 1.0f / 11.0f;
    p = p * s2 + 1.0f / 9.0f;
    p = p * s2 + 1.0f / 7.0f;
    p = p * s2 + 1.0f / 5.0f;
    p = p * s2 + 1.0f / 3.0f;
    p = p * s2 + 1.0f;
    return 2.0f * s * p;
}

// softplus(x) = max(x, 0) + log(1 + e), e = exp(-|x|) in (0, 1]; log(1 + e) = 2 atanh(s), s = e / (2 + e)
// in (0, 1/3]. Also returns sigmoid(x).
inline vf softplus_v(vf x, vf* sig) {
    const vf e = exp_v(select(x > 0.0f, -x, x));
    const vf s = e / (2.0f + e);
    const vf inv = 1.0f / (1.0f + e);
    *sig = select(x >= 0.0f, inv, e * inv);
    return vmax(x, splat(0.0f)) + two_atanh_v(s);
}

// softplus(x) for the inference forward: softplus_v's series without its sigmoid and with s = e / (2 + e) as e times
// a reciprocal from vrcp14ps refined by one Newton step (relative error ~2^-28, under float rounding) instead of a
// division (the step pass's costliest instruction). AVX-512 only; elsewhere softplus_v.
inline vf softplus_fast_v(vf x) {
#if defined(__AVX512F__)
    const vf e = exp_v(select(x > 0.0f, -x, x));
    const vf den = 2.0f + e;
    vf r = (vf)_mm512_rcp14_ps((__m512)den);
    r = r * (2.0f - den * r);
    return vmax(x, splat(0.0f)) + two_atanh_v(e * r);
#else
    vf sig;
    return softplus_v(x, &sig);
#endif
}

// out[n] = sum_j P[n][j] for 16 vectors P[0..15] (a transposing tree: 15 adds, 30 shuffles).
inline vf transpose_sum16(const vf* P) {
    vf q[8], r[4], s[2];
    for (int i = 0; i < 8; ++i)
        q[i] = __builtin_shufflevector(P[2 * i], P[2 * i + 1], 0, 1, 2, 3, 4, 5, 6, 7, 16, 17, 18, 19, 20, 21, 22, 23) +
               __builtin_shufflevector(P[2 * i], P[2 * i + 1], 8, 9, 10, 11, 12, 13, 14, 15, 24, 25, 26, 27, 28, 29, 30, 31);
    for (int i = 0; i < 4; ++i)
        r[i] = __builtin_shufflevector(q[2 * i], q[2 * i + 1], 0, 1, 2, 3, 8, 9, 10, 11, 16, 17, 18, 19, 24, 25, 26, 27) +
               __builtin_shufflevector(q[2 * i], q[2 * i + 1], 4, 5, 6, 7, 12, 13, 14, 15, 20, 21, 22, 23, 28, 29, 30, 31);
    for (int i = 0; i < 2; ++i)
        s[i] = __builtin_shufflevector(r[2 * i], r[2 * i + 1], 0, 1, 4, 5, 8, 9, 12, 13, 16, 17, 20, 21, 24, 25, 28, 29) +
               __builtin_shufflevector(r[2 * i], r[2 * i + 1], 2, 3, 6, 7, 10, 11, 14, 15, 18, 19, 22, 23, 26, 27, 30, 31);
    return __builtin_shufflevector(s[0], s[1], 0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 22, 24, 26, 28, 30) +
           __builtin_shufflevector(s[0], s[1], 1, 3, 5, 7, 9, 11, 13, 15, 17, 19, 21, 23, 25, 27, 29, 31);
}

inline float hsum(vf v) {
    alignas(64) float t[W];
    storev(t, v);
    float s = 0.0f;
    for (int j = 0; j < W; ++j) s += t[j];
    return s;
}

// out[j] = sum over the lanes of P[j], j < R: a reduction per vector for a few (one shuffle tree each), transposing
// trees of 16 for more (R = 16: one tree of 45 operations where 16 reductions take about 130).
inline void lane_sums(const vf* P, int64_t R, float* out) {
#if defined(__AVX512F__)
    if (R <= 3) {
        for (int64_t j = 0; j < R; ++j) out[j] = _mm512_reduce_add_ps((__m512)P[j]);
        return;
    }
#endif
    for (int64_t j0 = 0; j0 < R; j0 += W) {
        const int64_t m = std::min<int64_t>(W, R - j0);
        vf t[W];
        for (int64_t i = 0; i < W; ++i) t[i] = i < m ? P[j0 + i] : splat(0.0f);
        alignas(64) float sums[W];
        storev(sums, transpose_sum16(t));
        for (int64_t i = 0; i < m; ++i) out[j0 + i] = sums[i];
    }
}

// Positions pi_g(l), pi_g(l + 1), ... of one scan direction, one step at a time without a division (the column-
// major directions cost two 64-bit divisions per step, and as many for the prefetch address, when computed
// from l): p moves by s_in within an image column (row), and by s_out more after n_in steps.
struct PosIter {
    int64_t p, cnt, n_in, s_in, s_out;
    inline void next() {
        p += s_in;
        if (++cnt == n_in) {
            cnt = 0;
            p += s_out;
        }
    }
};

struct Geometry {
    int64_t batch, L, G, Dg, N, Du, H, Wd;
    bool ss2d;
    // the positions of group (direction) g from scan step l0 on: row-major, column-major (step l = j H + i reads
    // i Wd + j), and both reversed; the plain scan reads p = l
    inline PosIter walk(int64_t g, int64_t l0) const {
        constexpr int64_t never = INT64_MAX;
        if (!ss2d || g == 0) return {l0, 0, never, 1, 0};
        if (g == 2) return {L - 1 - l0, 0, never, -1, 0};
        if (g == 1) {
            const int64_t i = l0 % H, j = l0 / H;
            return {i * Wd + j, i, H, Wd, 1 - H * Wd};
        }
        const int64_t l = L - 1 - l0, i = l % H, j = l / H;  // g == 3: column-major, reversed
        return {i * Wd + j, H - 1 - i, H, -Wd, H * Wd - 1};
    }
};

struct Strides4 {
    int64_t b, l, g, n;
};

inline Strides4 strides4(const at::Tensor& t) { return {t.stride(0), t.stride(1), t.stride(2), t.stride(3)}; }

struct Strides3 {
    int64_t b, l, c;
};

inline Strides3 strides3(const at::Tensor& t) { return {t.stride(0), t.stride(1), t.stride(2)}; }

void check_inputs(const at::Tensor& u, const at::Tensor& delta, const at::Tensor& A, const at::Tensor& B,
                  const at::Tensor& C, const at::Tensor& D, const at::Tensor& bias, const Geometry& geo) {
    // delta undefined: the fused dt projection (ss2d_fwd_lowrank), which checks its own inputs
    for (const at::Tensor* t : {&u, &delta, &A, &B, &C}) {
        if (t == &delta && !delta.defined()) continue;
        TORCH_CHECK(t->device().is_cpu() && t->scalar_type() == at::kFloat, "selective_scan_cpu: float32 CPU tensors expected");
    }
    // u and delta: any strides (channels-last is fastest; a (batch, dim, L) tensor viewed as (batch, L, dim) is
    // read with gathered lanes); outputs are allocated with the same strides
    TORCH_CHECK(u.dim() == 3 && u.is_non_overlapping_and_dense(), "selective_scan_cpu: u must be a dense (batch, L, Du) tensor");
    TORCH_CHECK(!delta.defined() || (delta.dim() == 3 && delta.is_non_overlapping_and_dense()), "selective_scan_cpu: delta must be a dense (batch, L, dim) tensor");
    TORCH_CHECK(A.dim() == 2 && A.is_contiguous(), "selective_scan_cpu: A must be a contiguous (dim, N) tensor");
    TORCH_CHECK(B.dim() == 4 && C.dim() == 4, "selective_scan_cpu: B and C must be (batch, L, G, N)");
    TORCH_CHECK(geo.N <= NMAX, "selective_scan_cpu: d_state must be <= ", NMAX);
    TORCH_CHECK(u.size(0) == geo.batch && u.size(1) == geo.L && (!delta.defined() || (delta.size(0) == geo.batch && delta.size(1) == geo.L && delta.size(2) == geo.G * geo.Dg)), "selective_scan_cpu: shape mismatch");
    TORCH_CHECK(B.size(1) == geo.L && B.size(2) == geo.G && B.size(3) == geo.N && C.sizes() == B.sizes(), "selective_scan_cpu: B/C shape mismatch");
    for (const at::Tensor* t : {&D, &bias}) {
        if (t->defined()) {
            TORCH_CHECK(t->is_contiguous() && t->numel() == geo.G * geo.Dg && t->scalar_type() == at::kFloat,
                        "selective_scan_cpu: D / bias must be contiguous float32 (dim,)");
        }
    }
    if (geo.ss2d) {
        TORCH_CHECK(geo.G == 4 && geo.H * geo.Wd == geo.L && geo.Du == geo.Dg, "selective_scan_cpu: SS2D needs 4 directions over H x W");
    } else {
        TORCH_CHECK(geo.Du == geo.G * geo.Dg, "selective_scan_cpu: u must have dim channels");
    }
}

Geometry make_geometry(const at::Tensor& u, const at::Tensor& A, const at::Tensor& B, bool ss2d, int64_t H, int64_t Wd) {
    Geometry geo;
    geo.batch = u.size(0);
    geo.L = u.size(1);
    geo.Du = u.size(2);
    geo.G = B.size(2);
    geo.N = A.size(1);
    geo.Dg = A.size(0) / geo.G;
    geo.ss2d = ss2d;
    geo.H = H;
    geo.Wd = Wd;
    return geo;
}


// Per-block constants in lanes (inactive lanes: A = D = bias = 0, mask = 0).
struct BlockParams {
    vf A[NMAX];
    vf D, bias, mask;
    vf Wdt[RMAX];  // the dt projection's weights W[c, j] in lanes (ss2d_fwd_lowrank only)
};

inline void load_dt_weight(BlockParams& p, const float* Wdt, int64_t R, int64_t c0, int nw) {
    alignas(64) float t[W];
    for (int64_t j = 0; j < R; ++j) {
        for (int i = 0; i < W; ++i) t[i] = i < nw ? Wdt[(c0 + i) * R + j] : 0.0f;
        p.Wdt[j] = loadv(t);
    }
}

inline void load_params(BlockParams& p, const float* A, const float* D, const float* bias, int64_t c0, int nw, int64_t N) {
    alignas(64) float t[W];
    for (int64_t n = 0; n < N; ++n) {
        for (int j = 0; j < W; ++j) t[j] = j < nw ? A[(c0 + j) * N + n] : 0.0f;
        p.A[n] = loadv(t);
    }
    for (int j = 0; j < W; ++j) t[j] = (D != nullptr && j < nw) ? D[c0 + j] : 0.0f;
    p.D = loadv(t);
    for (int j = 0; j < W; ++j) t[j] = (bias != nullptr && j < nw) ? bias[c0 + j] : 0.0f;
    p.bias = loadv(t);
    for (int j = 0; j < W; ++j) t[j] = j < nw ? 1.0f : 0.0f;
    p.mask = loadv(t);
}

// The fused dt projection's raw step of a lane block at one position: sum_j W[c, j] dt_low[p, g, j] (row: dt_low at
// (p, g), its R entries at stride sn), in one order for the forward and the backward's recomputation.
inline vf lowrank_step(const BlockParams& p, const float* row, int64_t R, int64_t sn) {
    vf raw = p.Wdt[0] * row[0];
    for (int64_t j = 1; j < R; ++j) raw += p.Wdt[j] * row[j * sn];
    return raw;
}

// delta (after bias / softplus) and its derivative w.r.t. the raw delta, in lanes (inactive lanes: 0). FAST (the
// inference forward, which needs no derivative): softplus_fast_v, and dsig is left unset.
template <bool FAST = false>
inline vf step_delta(vf raw, const BlockParams& p, bool softplus, vf* dsig) {
    if (!softplus) {
        *dsig = splat(1.0f);
        return raw + p.bias;
    }
    return (FAST ? softplus_fast_v(raw + p.bias) : softplus_v(raw + p.bias, dsig)) * p.mask;
}

struct FwdArgs {
    Geometry geo;
    int64_t nblk, nck, chunk;
    int64_t parts, per_part;  // tasks per batch element, each walking per_part lane blocks together (see scan_fwd)
    bool softplus;
    const float *u, *delta, *A, *B, *C, *D, *bias;
    float *y, *ck;
    Strides4 sB, sC;
    Strides3 su, sd;  // (batch, position, channel) strides of u / y and of delta
    // the fused dt projection (ss2d_fwd_lowrank; delta is then unused): the raw step of channel c of group g at
    // position p is sum_j dtl[b, p, g, j] Wdt[g Dg + c, j]; dtl (batch, L, G, R) any strides, Wdt (G Dg, R)
    const float *dtl = nullptr, *Wdt = nullptr;
    Strides4 sdt{};
    int64_t R = 0;
};

struct BwdArgs {
    Geometry geo;
    int64_t nblk, nck, chunk;
    int64_t parts, per_part;  // tasks per batch element, each walking per_part lane blocks (see scan_bwd)
    bool softplus;
    const float *u, *delta, *A, *B, *C, *D, *bias, *ck, *dy;
    float *du, *ddelta, *dA, *dB, *dC, *dD, *dbias;
    Strides4 sB, sC;
    Strides3 su, sd, sdy;  // u / du, delta / ddelta, dy
    // the fused dt projection (ss2d_bwd_lowrank; delta and ddelta are then unused): the raw steps recomputed from
    // dtl (batch, L, G, R) any strides and Wdt (G Dg, R), as the forward computed them; instead of d(raw step) per
    // channel, its two products: ddtl (parts, batch, L, G, R), d dt_low summed over a part's channels (the part's
    // first block writes, its later blocks add; the caller sums the parts), and dWdt (batch, G Dg, R)
    const float *dtl = nullptr, *Wdt = nullptr;
    Strides4 sdt{};
    int64_t R = 0;
    float *ddtl = nullptr, *dWdt = nullptr;
};

// Forward tasks, taken from next() until it returns -1. NT = d_state known at compile time (the state loop unrolls
// and the state vectors stay in registers), or 0 = runtime d_state.
// A task is (batch element, part): a part is a range of lane blocks (FwdArgs::per_part of them), walked together
// chunk by chunk, so that a chunk's rows of B and C (shared by a group's channels) are read from memory by the
// part's first block and from cache by the others. Per chunk and block, two passes: the first reads every step's
// delta and u, computes the step (softplus), delta u and D u into small buffers and prefetches rows read later;
// the second runs the recurrence from the buffers (its N states in registers; a block's states are kept in Hsave
// between chunks). The steps' softplus (an exp, a division, a series: ~100 cycles of dependent latency) is then
// off the recurrence's path, and the out-of-order core overlaps the state updates of consecutive steps. How the
// blocks are split into parts does not change any lane's arithmetic: the results do not depend on it.
template <int NT, bool FAST, class Next>
void fwd_tasks_body(const FwdArgs& a, Next next);

template <int NT, bool FAST, class Next>
void fwd_tasks(const FwdArgs& a, Next next) {
    decay_scope([&] { fwd_tasks_body<NT, FAST>(a, next); });
}

template <int NT, bool FAST, class Next>
void fwd_tasks_body(const FwdArgs& a, Next next) {
    const Geometry& geo = a.geo;
    const int64_t N = NT > 0 ? NT : geo.N, L = geo.L, G = geo.G, Dg = geo.Dg;
    const int64_t nblk = a.nblk, nck = a.nck, chunk = a.chunk, parts = a.parts, per_part = a.per_part;
    const bool ss2d = geo.ss2d;
    const Strides4 sB = a.sB, sC = a.sC, sdt = a.sdt;
    const Strides3 su = a.su, sd = a.sd;
    const bool lowrank = a.dtl != nullptr;
    const int64_t R = a.R;
    std::vector<BlockParams> prms(per_part);
    std::vector<vf> Hsave(per_part * N);
    vf h[NT > 0 ? NT : NMAX];
    std::vector<vf> DLbuf(chunk), DUbuf(chunk), YDbuf(chunk);
    std::vector<int64_t> Pbuf(chunk);
    for (int64_t task = next(); task >= 0; task = next()) {
        const int64_t b = task / parts, part = task % parts;
        const int64_t blk0 = part * per_part, nb = std::min(nblk, blk0 + per_part) - blk0;
        for (int64_t g = 0; g < G; ++g) {
            for (int64_t i = 0; i < nb; ++i) {
                const int64_t d0 = (blk0 + i) * W;
                load_params(prms[i], a.A, a.D, a.bias, g * Dg + d0, static_cast<int>(std::min<int64_t>(W, Dg - d0)), N);
                if (EXP2) {  // exp(delta A) = 2^(delta A log2(e))
                    for (int64_t n = 0; n < N; ++n) prms[i].A[n] = prms[i].A[n] * 1.4426950408889634f;
                }
                if (lowrank) load_dt_weight(prms[i], a.Wdt, R, g * Dg + d0, static_cast<int>(std::min<int64_t>(W, Dg - d0)));
                for (int64_t n = 0; n < N; ++n) Hsave[i * N + n] = splat(0.0f);
            }
            const float* Bbase = a.B + b * sB.b + g * sB.g;
            const float* Cbase = a.C + b * sC.b + g * sC.g;
            const float* dtbase = lowrank ? a.dtl + b * sdt.b + g * sdt.g : nullptr;
            const bool accumulate = ss2d && g > 0;  // SS2D: direction 0 writes y, directions 1-3 add to it
            for (int64_t k = 0; k < nck; ++k) {
                const int64_t T = std::min(chunk, L - k * chunk);
                const bool more = k + 1 < nck;
                for (int64_t i = 0; i < nb; ++i) {
                    const int64_t blk = blk0 + i, d0 = blk * W;
                    const int nw = static_cast<int>(std::min<int64_t>(W, Dg - d0));
                    const BlockParams& prm = prms[i];
                    const int64_t c0 = g * Dg + d0;      // channel of lane 0
                    const int64_t uc0 = ss2d ? d0 : c0;  // u / y column of lane 0
                    const float* dbase = lowrank ? nullptr : a.delta + b * sd.b + c0 * sd.c;
                    const float* ubase = a.u + b * su.b + uc0 * su.c;
                    float* ybase = a.y + b * su.b + uc0 * su.c;
                    for (int64_t n = 0; n < N; ++n) h[n] = Hsave[i * N + n];
                    if (a.ck != nullptr) {  // the state entering the chunk
                        float* ckg = a.ck + (((b * nblk + blk) * G + g) * nck) * N * W;
                        for (int64_t n = 0; n < N; ++n) storev(ckg + (k * N + n) * W, h[n]);
                    }
                    PosIter it = geo.walk(g, k * chunk);
                    PosIter ahead = geo.walk(g, std::min((k + 1) * chunk, L - 1));  // the next chunk's positions
                    for (int64_t s = 0; s < T; ++s, it.next()) {
                        const int64_t p = it.p;
                        Pbuf[s] = p;
                        if (more && (k + 1) * chunk + s < L) {  // delta and u a chunk ahead (each step reads a new line)
                            if (!lowrank) {
                                __builtin_prefetch(dbase + ahead.p * sd.l);
                            } else if (i == 0) {  // the low-rank steps' row, shared by the part's blocks
                                __builtin_prefetch(dtbase + ahead.p * sdt.l);
                            }
                            __builtin_prefetch(ubase + ahead.p * su.l);
                            ahead.next();
                        }
                        if (i == 0) {  // the part's later blocks find these rows in cache
                            __builtin_prefetch(Bbase + p * sB.l);
                            __builtin_prefetch(Bbase + p * sB.l + (N - 1) * sB.n);
                            __builtin_prefetch(Cbase + p * sC.l);
                            __builtin_prefetch(Cbase + p * sC.l + (N - 1) * sC.n);
                        }
                        __builtin_prefetch(ybase + p * su.l, 1);
                        vf raw;
                        if (lowrank) {  // the dt projection: R multiply-adds of broadcast low-rank steps
                            raw = lowrank_step(prm, dtbase + p * sdt.l, R, sdt.n);
                        } else {
                            raw = load_lanes(dbase + p * sd.l, sd.c, nw);
                        }
                        vf dsig;
                        const vf dl = step_delta<FAST>(raw, prm, a.softplus, &dsig);
                        const vf uu = load_lanes(ubase + p * su.l, su.c, nw);
                        DLbuf[s] = dl;
                        DUbuf[s] = dl * uu;
                        YDbuf[s] = prm.D * uu;
                    }
                    for (int64_t s = 0; s < T; ++s) {
                        const int64_t p = Pbuf[s];
                        const vf dl = DLbuf[s], du = DUbuf[s];
                        const float* Bl = Bbase + p * sB.l;
                        const float* Cl = Cbase + p * sC.l;
                        // C_t . h_t in 4 partial sums: one running sum chains N multiply-adds (4 cycles each) per step
                        vf ys[4] = {YDbuf[s], splat(0.0f), splat(0.0f), splat(0.0f)};
#pragma GCC unroll 16
                        for (int64_t n = 0; n < N; ++n) {
                            const vf decay = EXP2 ? exp2_v(dl * prm.A[n]) : exp_v(dl * prm.A[n]);
                            h[n] = decay * h[n] + du * Bl[n * sB.n];
                            ys[n & 3] += h[n] * Cl[n * sC.n];
                        }
                        vf yy = (ys[0] + ys[1]) + (ys[2] + ys[3]);
                        float* yrow = ybase + p * su.l;
                        if (accumulate) yy += load_lanes(yrow, su.c, nw);
                        store_lanes(yrow, su.c, yy, nw);
                    }
                    for (int64_t n = 0; n < N; ++n) Hsave[i * N + n] = h[n];
                }
            }
        }
    }
}

// Backward tasks, taken from next() until it returns -1 (NT as in fwd_tasks). Per chunk, newest first: a pass over
// the chunk's steps (positions, steps and their softplus derivative, u; prefetches of the rows read later), the
// recomputation of the chunk's states and decays from its checkpoint, and the adjoint recursion.
template <int NT, class Next>
void bwd_tasks_body(const BwdArgs& a, Next next);

template <int NT, class Next>
void bwd_tasks(const BwdArgs& a, Next next) {
    decay_scope([&] { bwd_tasks_body<NT>(a, next); });
}

template <int NT, class Next>
void bwd_tasks_body(const BwdArgs& a, Next next) {
    const Geometry& geo = a.geo;
    const int64_t N = NT > 0 ? NT : geo.N, L = geo.L, G = geo.G, Dg = geo.Dg, Dall = G * Dg;
    const int64_t nblk = a.nblk, nck = a.nck, chunk = a.chunk;
    const bool ss2d = geo.ss2d;
    const Strides4 sB = a.sB, sC = a.sC;
    const Strides3 su = a.su, sd = a.sd, sdy = a.sdy;
    BlockParams prm;
    // per chunk: states h_t and decays a_t (T x N vectors), steps, sigmoids, inputs (T vectors), positions
    std::vector<vf> Hbuf(chunk * N), Abuf(chunk * N), DLbuf(chunk), SGbuf(chunk), Ubuf(chunk);
    std::vector<int64_t> Pbuf(chunk);
    constexpr int NA = NT > 0 ? NT : NMAX;
    vf h[NA], gn[NA], dAacc[NA], pB[NA], pC[NA], A2[NA];
    alignas(64) float sums[W];
    const int64_t parts = a.parts, per_part = a.per_part;
    const bool lowrank = a.dtl != nullptr;
    const int64_t R = a.R;
    const Strides4 sdt = a.sdt;
    vf dWacc[RMAX], pW[RMAX];
    float dts[RMAX];
    for (int64_t task = next(); task >= 0; task = next()) {
        const int64_t b = task / parts, part = task % parts;
        const int64_t blk0 = part * per_part, blk1 = std::min(nblk, blk0 + per_part);
        for (int64_t blk = blk0; blk < blk1; ++blk) {
            const int64_t d0 = blk * W;
            const int nw = static_cast<int>(std::min<int64_t>(W, Dg - d0));
            // dB_t, dC_t (shared by the group's channels): the part's first block writes them, its later blocks add
            const bool add_dBC = blk > blk0;
            for (int64_t g = 0; g < G; ++g) {
                const int64_t c0 = g * Dg + d0;
                const int64_t uc0 = ss2d ? d0 : c0;
                load_params(prm, a.A, a.D, a.bias, c0, nw, N);
                for (int64_t n = 0; n < N; ++n) {
                    gn[n] = splat(0.0f);  // a_{t+1} g_{t+1}, carried backwards
                    dAacc[n] = splat(0.0f);
                    A2[n] = prm.A[n] * 1.4426950408889634f;  // the forward's exp2 argument, A log2(e)
                }
                if (lowrank) {
                    load_dt_weight(prm, a.Wdt, R, c0, nw);
                    for (int64_t j = 0; j < R; ++j) dWacc[j] = splat(0.0f);
                }
                const float* dtbase = lowrank ? a.dtl + b * sdt.b + g * sdt.g : nullptr;
                float* ddtbase = lowrank ? a.ddtl + ((part * geo.batch + b) * L * G + g) * R : nullptr;
                vf dDacc = splat(0.0f), dbacc = splat(0.0f);
                const float* dbase = lowrank ? nullptr : a.delta + b * sd.b + c0 * sd.c;
                float* ddbase = lowrank ? nullptr : a.ddelta + b * sd.b + c0 * sd.c;
                const float* ubase = a.u + b * su.b + uc0 * su.c;
                float* dubase = a.du + b * su.b + uc0 * su.c;
                const float* dybase = a.dy + b * sdy.b + uc0 * sdy.c;
                const float* Bbase = a.B + b * sB.b + g * sB.g;
                const float* Cbase = a.C + b * sC.b + g * sC.g;
                float* dBbase = a.dB + ((part * geo.batch + b) * L * G + g) * N;  // (parts, batch, L, G, N)
                float* dCbase = a.dC + ((part * geo.batch + b) * L * G + g) * N;
                const bool accumulate = ss2d && g > 0;  // SS2D: direction 0 writes du, directions 1-3 add to it
                const float* ckg = a.ck + (((b * nblk + blk) * G + g) * nck) * N * W;
                for (int64_t k = nck - 1; k >= 0; --k) {
                    const int64_t t0 = k * chunk, T = std::min(chunk, L - t0);
                    PosIter it = geo.walk(g, t0);
                    PosIter ahead = geo.walk(g, k > 0 ? t0 - chunk : 0);  // the chunk done next, for prefetches
                    for (int64_t s = 0; s < T; ++s, it.next()) {
                        const int64_t p = it.p;
                        Pbuf[s] = p;
                        if (k > 0 && s < chunk) {  // delta and u of the previous chunk (each step reads a new line)
                            __builtin_prefetch(lowrank ? dtbase + ahead.p * sdt.l : dbase + ahead.p * sd.l);
                            __builtin_prefetch(ubase + ahead.p * su.l);
                            ahead.next();
                        }
                        __builtin_prefetch(Bbase + p * sB.l);
                        __builtin_prefetch(Cbase + p * sC.l);
                        __builtin_prefetch(dybase + p * sdy.l);
                        if (accumulate) __builtin_prefetch(dubase + p * su.l, 1);
                        vf dsig, raw;
                        if (lowrank) {  // the forward's dt projection, in the forward's order
                            raw = lowrank_step(prm, dtbase + p * sdt.l, R, sdt.n);
                        } else {
                            raw = load_lanes(dbase + p * sd.l, sd.c, nw);
                        }
                        DLbuf[s] = step_delta(raw, prm, a.softplus, &dsig);
                        SGbuf[s] = dsig;
                        Ubuf[s] = load_lanes(ubase + p * su.l, su.c, nw);
                    }
                    // recompute the chunk's states and decays
                    for (int64_t n = 0; n < N; ++n) h[n] = loadv(ckg + (k * N + n) * W);
                    for (int64_t s = 0; s < T; ++s) {
                        const vf dl = DLbuf[s];
                        const vf du = dl * Ubuf[s];
                        const float* Bl = Bbase + Pbuf[s] * sB.l;
                        vf* Hs = &Hbuf[s * N];
                        vf* As = &Abuf[s * N];
#pragma GCC unroll 16
                        for (int64_t n = 0; n < N; ++n) {
                            const vf decay = EXP2 ? exp2_v(dl * A2[n]) : exp_v(dl * prm.A[n]);
                            h[n] = decay * h[n] + du * Bl[n * sB.n];
                            As[n] = decay;
                            Hs[n] = h[n];
                        }
                    }
                    // adjoint recursion g_t = C_t dy_t + a_{t+1} g_{t+1}, newest position first
                    for (int64_t s = T - 1; s >= 0; --s) {
                        const int64_t p = Pbuf[s];
                        if (s >= ADJ_AHEAD) {  // the recomputation's buffers have evicted these rows from L1
                            const int64_t q = Pbuf[s - ADJ_AHEAD];
                            __builtin_prefetch(Bbase + q * sB.l);
                            __builtin_prefetch(Cbase + q * sC.l);
                            __builtin_prefetch(dybase + q * sdy.l);
                            if (lowrank) {
                                __builtin_prefetch(dtbase + q * sdt.l);
                                __builtin_prefetch(ddtbase + q * G * R, 1);
                            } else {
                                __builtin_prefetch(ddbase + q * sd.l, 1);
                            }
                            __builtin_prefetch(dubase + q * su.l, 1);
                        }
                        const vf dl = DLbuf[s], uu = Ubuf[s];
                        const vf* Hs = &Hbuf[s * N];
                        const vf* As = &Abuf[s * N];
                        const float* Bl = Bbase + p * sB.l;
                        const float* Cl = Cbase + p * sC.l;
                        const vf dyv = load_lanes(dybase + p * sdy.l, sdy.c, nw);
                        const vf du = dl * uu;
                        // sum_n g_n A_n a_n h_{t-1,n} and sum_n g_n B_n, each in 4 partial sums (one running sum would
                        // chain N multiply-adds per step)
                        vf dsums[4] = {}, ssums[4] = {};
#pragma GCC unroll 16
                        for (int64_t n = 0; n < N; ++n) {
                            const float bn = Bl[n * sB.n];
                            const vf gt = dyv * Cl[n * sC.n] + gn[n];
                            const vf gah = gt * (Hs[n] - du * bn);  // a_t h_{t-1} = h_t - delta u B
                            dsums[n & 3] += prm.A[n] * gah;
                            dAacc[n] += dl * gah;
                            ssums[n & 3] += gt * bn;
                            pB[n] = gt * du;
                            pC[n] = Hs[n] * dyv;
                            gn[n] = As[n] * gt;
                        }
                        const vf dsum = (dsums[0] + dsums[1]) + (dsums[2] + dsums[3]);
                        const vf ssum = (ssums[0] + ssums[1]) + (ssums[2] + ssums[3]);
                        float* dBrow = dBbase + p * G * N;
                        float* dCrow = dCbase + p * G * N;
                        if constexpr (NT == W) {
                            vf sB16 = transpose_sum16(pB), sC16 = transpose_sum16(pC);  // dB_t[n], dC_t[n]: lane sums
                            if (add_dBC) {
                                sB16 += loadv(dBrow);
                                sC16 += loadv(dCrow);
                            }
                            storev(dBrow, sB16);
                            storev(dCrow, sC16);
                        } else {
                            for (int64_t n = 0; n < N; ++n) {
                                dBrow[n] = add_dBC ? dBrow[n] + hsum(pB[n]) : hsum(pB[n]);
                                dCrow[n] = add_dBC ? dCrow[n] + hsum(pC[n]) : hsum(pC[n]);
                            }
                        }
                        // d delta_t = sum_n g_n (A_n a_n h_{t-1,n} + u B_n); through softplus: * sigmoid
                        const vf ddl = (dsum + uu * ssum) * SGbuf[s];
                        dbacc += ddl;
                        dDacc += dyv * uu;
                        if (lowrank) {
                            // the dt projection's gradients: dW[c, j] += ddl[c] dt_low[p, g, j] (per lane), and
                            // d dt_low[p, g, j] = sum over the channels of ddl[c] W[c, j] (lane sums, then the part's
                            // blocks in turn)
                            const float* row = dtbase + p * sdt.l;
                            for (int64_t j = 0; j < R; ++j) {
                                dWacc[j] += ddl * row[j * sdt.n];
                                pW[j] = ddl * prm.Wdt[j];
                            }
                            lane_sums(pW, R, dts);
                            float* drow = ddtbase + p * G * R;
                            for (int64_t j = 0; j < R; ++j) drow[j] = add_dBC ? drow[j] + dts[j] : dts[j];
                        } else {
                            store_lanes(ddbase + p * sd.l, sd.c, ddl, nw);
                        }
                        vf dU = dl * ssum + prm.D * dyv;  // dL/du_t
                        float* durow = dubase + p * su.l;
                        if (accumulate) dU += load_lanes(durow, su.c, nw);
                        store_lanes(durow, su.c, dU, nw);
                    }
                }
                for (int64_t n = 0; n < N; ++n) {
                    storev(sums, dAacc[n]);
                    for (int j = 0; j < nw; ++j) a.dA[(b * Dall + c0 + j) * N + n] = sums[j];
                }
                storev(sums, dDacc);
                for (int j = 0; j < nw; ++j) a.dD[b * Dall + c0 + j] = sums[j];
                storev(sums, dbacc);
                for (int j = 0; j < nw; ++j) a.dbias[b * Dall + c0 + j] = sums[j];
                for (int64_t j = 0; lowrank && j < R; ++j) {
                    storev(sums, dWacc[j]);
                    for (int i = 0; i < nw; ++i) a.dWdt[(b * Dall + c0 + i) * R + j] = sums[i];
                }
            }
        }
    }
}

// The lane blocks cut into ranges, one task per (batch element, range): as few ranges as give each batch element
// ceil(tasks / batch) tasks (at most nblk), none empty.
struct BlockSplit {
    int64_t parts, per_part;
};

inline BlockSplit split_blocks(int64_t nblk, int64_t batch, int64_t tasks) {
    const int64_t wanted = std::min<int64_t>(nblk, (tasks + batch - 1) / batch);
    const int64_t per_part = (nblk + wanted - 1) / wanted;
    return {(nblk + per_part - 1) / per_part, per_part};
}

// Runs body(next) on torch's intra-op threads; next() hands out task indices 0..ntasks-1 one at a time
// (dynamic scheduling: on a shared machine a descheduled thread holds up one task, not half of them).
template <class Body>
void run_tasks(int64_t ntasks, Body body) {
    std::atomic<int64_t> counter{0};
    auto next = [&]() -> int64_t {
        const int64_t t = counter.fetch_add(1, std::memory_order_relaxed);
        return t < ntasks ? t : -1;
    };
    const int64_t workers = std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), ntasks));
    at::parallel_for(0, workers, 1, [&](int64_t begin, int64_t end) {
        if (begin < end) body(next);
    });
}

}  // namespace

namespace {

// The forward's body, shared by scan_fwd and ss2d_fwd_lowrank (the inputs checked by the caller; dtl / Wdt
// undefined unless the dt projection is fused).
std::vector<at::Tensor> fwd_impl(const at::Tensor& u, const at::Tensor& delta, const at::Tensor& A, const at::Tensor& B,
                                 const at::Tensor& C, const at::Tensor& D, const at::Tensor& bias, bool softplus,
                                 const Geometry& geo, int64_t chunk, const at::Tensor& dtl, const at::Tensor& Wdt) {
    // chunk <= 0: no backward will follow (inference): no checkpoints are written and ck comes back empty (at
    // 480 x 640 they are as large as y: 78 MB per call at DVSS level 0); the chunks are then only the unit of the
    // step pass (INFERENCE_CHUNK positions)
    const bool keep = chunk >= 1;
    if (!keep) chunk = INFERENCE_CHUNK;
    const int64_t nblk = (geo.Dg + W - 1) / W;
    const int64_t nck = (geo.L + chunk - 1) / chunk;
    at::Tensor y = at::empty_like(u);  // SS2D: direction 0 writes every position, 1-3 add to it
    // state entering each chunk: (batch, nblk, G, nck, N, W)
    at::Tensor ck = keep ? at::empty({geo.batch, nblk, geo.G, nck, geo.N, W}, u.options()) : at::empty({0}, u.options());
    const float* up = u.data_ptr<float>();
    const float* dp = delta.defined() ? delta.data_ptr<float>() : nullptr;
    const float* Ap = A.data_ptr<float>();
    const float* Bp = B.data_ptr<float>();
    const float* Cp = C.data_ptr<float>();
    const float* Dp = D.defined() ? D.data_ptr<float>() : nullptr;
    const float* bp = bias.defined() ? bias.data_ptr<float>() : nullptr;
    float* yp = y.data_ptr<float>();
    float* ckp = keep ? ck.data_ptr<float>() : nullptr;
    const Strides4 sB = strides4(B), sC = strides4(C);

    TORCH_CHECK(y.strides() == u.strides(), "selective_scan_cpu: output layout differs from u's");
    // Tasks: (batch element, part), a part being a range of lane blocks walked together chunk by chunk (their B and C
    // rows read once from memory). As few parts as keep every thread busy: ceil(threads / batch), at most nblk.
    const BlockSplit split = split_blocks(nblk, geo.batch, std::max<int64_t>(1, at::get_num_threads()));
    const int64_t parts = split.parts, per_part = split.per_part;
    FwdArgs args{geo, nblk, nck, chunk, parts, per_part, softplus, up, dp, Ap, Bp, Cp, Dp, bp, yp, ckp, sB, sC,
                 strides3(u), delta.defined() ? strides3(delta) : Strides3{}};
    if (dtl.defined()) {
        args.dtl = dtl.data_ptr<float>();
        args.Wdt = Wdt.data_ptr<float>();
        args.sdt = strides4(dtl);
        args.R = dtl.size(3);
    }
    // exp2_v for the decays on AVX-512 (the backward recomputes them the same way); inference (no checkpoints: no
    // backward, so no derivative) also takes softplus_fast_v
    const bool fast = !keep && HAVE_EXP2_FAST;
    run_tasks(geo.batch * parts, [&](auto next) {
        if (geo.N == 16) {
            fast ? fwd_tasks<16, true>(args, next) : fwd_tasks<16, false>(args, next);
        } else {
            fast ? fwd_tasks<0, true>(args, next) : fwd_tasks<0, false>(args, next);
        }
    });
    return {y, ck};
}

}  // namespace

std::vector<at::Tensor> scan_fwd(const at::Tensor& u, const at::Tensor& delta, const at::Tensor& A, const at::Tensor& B,
                                 const at::Tensor& C, const c10::optional<at::Tensor>& D_opt,
                                 const c10::optional<at::Tensor>& bias_opt, bool softplus, bool ss2d, int64_t H,
                                 int64_t Wd, int64_t chunk) {
    const at::Tensor D = D_opt.has_value() ? *D_opt : at::Tensor();
    const at::Tensor bias = bias_opt.has_value() ? *bias_opt : at::Tensor();
    const Geometry geo = make_geometry(u, A, B, ss2d, H, Wd);
    check_inputs(u, delta, A, B, C, D, bias, geo);
    return fwd_impl(u, delta, A, B, C, D, bias, softplus, geo, chunk, at::Tensor(), at::Tensor());
}

namespace {
void check_lowrank(const char* fn, const at::Tensor& dt_low, const at::Tensor& dt_weight, const Geometry& geo) {
    for (const at::Tensor* t : {&dt_low, &dt_weight}) {
        TORCH_CHECK(t->device().is_cpu() && t->scalar_type() == at::kFloat, fn, ": float32 CPU tensors expected");
    }
    TORCH_CHECK(dt_low.dim() == 4 && dt_low.size(0) == geo.batch && dt_low.size(1) == geo.L && dt_low.size(2) == geo.G,
                fn, ": dt_low must be (batch, L, 4, R)");
    const int64_t R = dt_low.size(3);
    TORCH_CHECK(R >= 1 && R <= RMAX, fn, ": dt_rank must be in 1..", RMAX, ", got ", R);
    TORCH_CHECK(dt_weight.dim() == 2 && dt_weight.is_contiguous() && dt_weight.size(0) == geo.G * geo.Dg &&
                    dt_weight.size(1) == R,
                fn, ": dt_weight must be a contiguous (4 d, R) tensor");
}

// The SS2D forward with its dt projection fused (ss2d_fwd_lowrank, ss2d_fwd_lowrank_train): the inputs checked,
// then fwd_impl with `chunk` (0: no checkpoints).
std::vector<at::Tensor> lowrank_fwd(const char* fn, const at::Tensor& u, const at::Tensor& dt_low,
                                    const at::Tensor& dt_weight, const at::Tensor& A, const at::Tensor& B,
                                    const at::Tensor& C, const c10::optional<at::Tensor>& D_opt,
                                    const c10::optional<at::Tensor>& bias_opt, int64_t H, int64_t Wd, int64_t chunk) {
    const at::Tensor D = D_opt.has_value() ? *D_opt : at::Tensor();
    const at::Tensor bias = bias_opt.has_value() ? *bias_opt : at::Tensor();
    const Geometry geo = make_geometry(u, A, B, true, H, Wd);
    check_lowrank(fn, dt_low, dt_weight, geo);
    check_inputs(u, at::Tensor(), A, B, C, D, bias, geo);
    return fwd_impl(u, at::Tensor(), A, B, C, D, bias, true, geo, chunk, dt_low, dt_weight);
}
}  // namespace

// The SS2D forward with its dt projection fused, for inference (no checkpoints: no backward can follow): the raw
// steps are not read from a (batch, L, 4 d) tensor but computed per position from the low-rank steps dt_low
// (batch, L, 4, R) (any strides: a slice of x_proj's output) and the weights dt_weight (4 d, R), then biased and
// passed through softplus as in scan_fwd. Returns y (batch, L, d).
at::Tensor ss2d_fwd_lowrank(const at::Tensor& u, const at::Tensor& dt_low, const at::Tensor& dt_weight,
                            const at::Tensor& A, const at::Tensor& B, const at::Tensor& C,
                            const c10::optional<at::Tensor>& D_opt, const c10::optional<at::Tensor>& bias_opt,
                            int64_t H, int64_t Wd) {
    return lowrank_fwd("ss2d_fwd_lowrank", u, dt_low, dt_weight, A, B, C, D_opt, bias_opt, H, Wd, 0)[0];
}

// The same forward for training: the checkpoints of every chunk of `chunk` positions kept for ss2d_bwd_lowrank, and
// the training forward's arithmetic (softplus_v: the backward's steps), as scan_fwd. Returns {y, ck}.
std::vector<at::Tensor> ss2d_fwd_lowrank_train(const at::Tensor& u, const at::Tensor& dt_low, const at::Tensor& dt_weight,
                                               const at::Tensor& A, const at::Tensor& B, const at::Tensor& C,
                                               const c10::optional<at::Tensor>& D_opt,
                                               const c10::optional<at::Tensor>& bias_opt, int64_t H, int64_t Wd,
                                               int64_t chunk) {
    TORCH_CHECK(chunk >= 1, "ss2d_fwd_lowrank_train: chunk must be >= 1 (the backward's checkpoints)");
    return lowrank_fwd("ss2d_fwd_lowrank_train", u, dt_low, dt_weight, A, B, C, D_opt, bias_opt, H, Wd, chunk);
}

namespace {
// The backward's body, shared by scan_bwd and ss2d_bwd_lowrank (dtl / Wdt undefined unless the dt projection is
// fused: then delta is undefined, and the last two outputs are d dt_low (batch, L, G, R) and d dt_weight (G Dg, R)
// in place of d delta).
std::vector<at::Tensor> bwd_impl(const at::Tensor& u, const at::Tensor& delta, const at::Tensor& A, const at::Tensor& B,
                                 const at::Tensor& C, const at::Tensor& D, const at::Tensor& bias, bool softplus,
                                 const Geometry& geo, int64_t chunk, const at::Tensor& ck, const at::Tensor& dy_in,
                                 const at::Tensor& dtl, const at::Tensor& Wdt) {
    const bool lowrank = dtl.defined();
    const at::Tensor& dy = dy_in;  // any strides (autograd may hand over an expanded or transposed gradient)
    TORCH_CHECK(dy.sizes() == u.sizes() && dy.scalar_type() == at::kFloat, "selective_scan_cpu: dy must have y's shape");
    TORCH_CHECK(chunk >= 1, "selective_scan_cpu: the backward needs the forward's checkpoints (chunk >= 1)");
    const int64_t nblk = (geo.Dg + W - 1) / W;
    const int64_t nck = (geo.L + chunk - 1) / chunk;
    TORCH_CHECK(ck.is_contiguous() && ck.numel() == geo.batch * nblk * geo.G * nck * geo.N * W, "selective_scan_cpu: bad checkpoints");
    const int64_t N = geo.N, L = geo.L, G = geo.G, Dg = geo.Dg, Du = geo.Du, Dall = G * Dg;

    at::Tensor du_out = at::empty_like(u);
    at::Tensor ddelta = lowrank ? at::Tensor() : at::empty_like(delta);
    TORCH_CHECK(du_out.strides() == u.strides() && (lowrank || ddelta.strides() == delta.strides()),
                "selective_scan_cpu: gradient layout differs");
    at::Tensor dA = at::empty({geo.batch, Dall, N}, u.options());
    // Tasks: (batch element, part), a part being a range of lane blocks walked in turn (its dB / dC rows summed in
    // place). One part per batch element from batch 4 on: no (lane blocks, batch, L, G, N) partial sums (at DVSS level
    // 0 of a 64x64 batch-4 step, 2 x 17 MB of fresh memory, first-touch page faults and a reduction pass); smaller
    // batches split the blocks into up to ceil(4 / batch) parts, so that 2+ threads have work. The split depends on
    // the shapes only: the sums, and so the results, do not depend on the number of threads.
    const BlockSplit split = split_blocks(nblk, geo.batch, 4);
    const int64_t parts = split.parts, per_part = split.per_part;
    at::Tensor dBp = at::empty({parts, geo.batch, L, G, N}, u.options());
    at::Tensor dCp = at::empty({parts, geo.batch, L, G, N}, u.options());
    at::Tensor dD = at::empty({geo.batch, Dall}, u.options());
    at::Tensor dbias = at::empty({geo.batch, Dall}, u.options());

    const float* up = u.data_ptr<float>();
    const float* dp = lowrank ? nullptr : delta.data_ptr<float>();
    const float* Ap = A.data_ptr<float>();
    const float* Bp = B.data_ptr<float>();
    const float* Cp = C.data_ptr<float>();
    const float* Dp = D.defined() ? D.data_ptr<float>() : nullptr;
    const float* bp = bias.defined() ? bias.data_ptr<float>() : nullptr;
    const float* ckp = ck.data_ptr<float>();
    const float* dyp = dy.data_ptr<float>();
    float* dup = du_out.data_ptr<float>();
    float* ddp = lowrank ? nullptr : ddelta.data_ptr<float>();
    float* dAp = dA.data_ptr<float>();
    float* dBpp = dBp.data_ptr<float>();
    float* dCpp = dCp.data_ptr<float>();
    float* dDp = dD.data_ptr<float>();
    float* dbp = dbias.data_ptr<float>();
    const Strides4 sB = strides4(B), sC = strides4(C);

    BwdArgs args{geo, nblk, nck, chunk, parts, per_part, softplus, up, dp, Ap, Bp, Cp, Dp, bp, ckp, dyp,
                 dup, ddp, dAp, dBpp, dCpp, dDp, dbp, sB, sC, strides3(u), lowrank ? Strides3{} : strides3(delta),
                 strides3(dy)};
    at::Tensor ddtlp, dWdt;
    if (lowrank) {
        const int64_t R = dtl.size(3);
        ddtlp = at::empty({parts, geo.batch, L, G, R}, u.options());
        dWdt = at::empty({geo.batch, Dall, R}, u.options());
        args.dtl = dtl.data_ptr<float>();
        args.Wdt = Wdt.data_ptr<float>();
        args.sdt = strides4(dtl);
        args.R = R;
        args.ddtl = ddtlp.data_ptr<float>();
        args.dWdt = dWdt.data_ptr<float>();
    }
    run_tasks(geo.batch * parts, [&](auto next) {
        if (geo.N == 16) {
            bwd_tasks<16>(args, next);
        } else {
            bwd_tasks<0>(args, next);
        }
    });
    at::Tensor dB = parts == 1 ? dBp.select(0, 0) : dBp.sum(0);
    at::Tensor dC = parts == 1 ? dCp.select(0, 0) : dCp.sum(0);
    if (lowrank) {
        at::Tensor ddtl = parts == 1 ? ddtlp.select(0, 0) : ddtlp.sum(0);
        return {du_out, ddtl, dA.sum(0), dB, dC, dD.sum(0), dbias.sum(0), dWdt.sum(0)};
    }
    return {du_out, ddelta, dA.sum(0), dB, dC, dD.sum(0), dbias.sum(0)};
}
}  // namespace

std::vector<at::Tensor> scan_bwd(const at::Tensor& u, const at::Tensor& delta, const at::Tensor& A, const at::Tensor& B,
                                 const at::Tensor& C, const c10::optional<at::Tensor>& D_opt,
                                 const c10::optional<at::Tensor>& bias_opt, bool softplus, bool ss2d, int64_t H,
                                 int64_t Wd, int64_t chunk, const at::Tensor& ck, const at::Tensor& dy) {
    const at::Tensor D = D_opt.has_value() ? *D_opt : at::Tensor();
    const at::Tensor bias = bias_opt.has_value() ? *bias_opt : at::Tensor();
    const Geometry geo = make_geometry(u, A, B, ss2d, H, Wd);
    check_inputs(u, delta, A, B, C, D, bias, geo);
    return bwd_impl(u, delta, A, B, C, D, bias, softplus, geo, chunk, ck, dy, at::Tensor(), at::Tensor());
}

// The backward of ss2d_fwd_lowrank_train: {du, d dt_low (batch, L, 4, R), dA, dB, dC, dD, dbias, d dt_weight (4 d,
// R)}. No (batch, L, 4 d) tensor of steps or of their gradient is written: the steps are recomputed from dt_low as
// the forward computed them, and their gradient goes straight into the dt projection's two products.
std::vector<at::Tensor> ss2d_bwd_lowrank(const at::Tensor& u, const at::Tensor& dt_low, const at::Tensor& dt_weight,
                                         const at::Tensor& A, const at::Tensor& B, const at::Tensor& C,
                                         const c10::optional<at::Tensor>& D_opt,
                                         const c10::optional<at::Tensor>& bias_opt, int64_t H, int64_t Wd,
                                         int64_t chunk, const at::Tensor& ck, const at::Tensor& dy) {
    const at::Tensor D = D_opt.has_value() ? *D_opt : at::Tensor();
    const at::Tensor bias = bias_opt.has_value() ? *bias_opt : at::Tensor();
    const Geometry geo = make_geometry(u, A, B, true, H, Wd);
    check_lowrank("ss2d_bwd_lowrank", dt_low, dt_weight, geo);
    check_inputs(u, at::Tensor(), A, B, C, D, bias, geo);
    return bwd_impl(u, at::Tensor(), A, B, C, D, bias, true, geo, chunk, ck, dy, dt_low, dt_weight);
}

// SS2D's output stage for inference, in place: y[r, :] <- LayerNorm(y[r, :]) * w + b, times SiLU(z[r, :]) = z / (1 +
// exp(-z)), row by row (a row: one position's d channels; y (rows, d) contiguous, z (rows, d) with any row stride,
// unit channel stride: a half of in_proj's output). One pass over y and z where LayerNorm, SiLU and the product
// each read and write a (rows, d) tensor. Mean and variance as two passes over the row in lanes (the variance of
// the centred values, as torch's LayerNorm, which it equals to rounding).
at::Tensor ss2d_out_gate(at::Tensor y, const at::Tensor& z, const at::Tensor& weight, const at::Tensor& bias, double eps) {
    TORCH_CHECK(y.device().is_cpu() && y.scalar_type() == at::kFloat && y.dim() == 2 && y.is_contiguous(),
                "ss2d_out_gate: y must be a contiguous float32 CPU (rows, d) tensor");
    const int64_t rows = y.size(0), d = y.size(1);
    TORCH_CHECK(z.scalar_type() == at::kFloat && z.dim() == 2 && z.size(0) == rows && z.size(1) == d && z.stride(1) == 1,
                "ss2d_out_gate: z must be a float32 (rows, d) tensor with unit channel stride");
    TORCH_CHECK(weight.is_contiguous() && bias.is_contiguous() && weight.numel() == d && bias.numel() == d &&
                    weight.scalar_type() == at::kFloat && bias.scalar_type() == at::kFloat,
                "ss2d_out_gate: weight and bias must be contiguous float32 (d,) tensors");
    float* yp = y.data_ptr<float>();
    const float* zp = z.data_ptr<float>();
    const float* wp = weight.data_ptr<float>();
    const float* bp = bias.data_ptr<float>();
    const int64_t sz = z.stride(0);
    const float inv_d = 1.0f / static_cast<float>(d);
    const float feps = static_cast<float>(eps);
    at::parallel_for(0, rows, 256, [&](int64_t begin, int64_t end) {
        for (int64_t r = begin; r < end; ++r) {
            float* yr = yp + r * d;
            const float* zr = zp + r * sz;
            vf acc = splat(0.0f);
            for (int64_t c = 0; c < d; c += W) acc += load_lanes(yr + c, static_cast<int>(std::min<int64_t>(W, d - c)));
            const float mean = hsum(acc) * inv_d;
            acc = splat(0.0f);
            for (int64_t c = 0; c < d; c += W) {
                const int nw = static_cast<int>(std::min<int64_t>(W, d - c));
                const vf v = (load_lanes(yr + c, nw) - mean) * load_lanes(zero_tail_mask(), nw);
                acc += v * v;
            }
            const float rstd = 1.0f / std::sqrt(hsum(acc) * inv_d + feps);
            for (int64_t c = 0; c < d; c += W) {
                const int nw = static_cast<int>(std::min<int64_t>(W, d - c));
                const vf zz = load_lanes(zr + c, nw);
                const vf gate = zz / (1.0f + exp_v(-zz));
                const vf v = ((load_lanes(yr + c, nw) - mean) * rstd * load_lanes(wp + c, nw) + load_lanes(bp + c, nw)) * gate;
                store_lanes(yr + c, v, nw);
            }
        }
    });
    return y;
}

// The roofline of the scan: a plain vectorised loop doing what one state update costs at least, one exp and
// three multiply-adds per element (decay argument, state update, readout), on L1-resident lanes. ``tasks``
// independent tasks of 256 elements x ``repeats`` sweeps (tasks x 256 x repeats updates in all); returns a
// checksum so that the work cannot be optimised away.
double roofline_loop(int64_t tasks, int64_t repeats) {
    std::vector<double> sums(tasks, 0.0);
    at::parallel_for(0, tasks, 1, [&](int64_t begin, int64_t end) {
        constexpr int M = 256 / W;
        for (int64_t task = begin; task < end; ++task) {
            vf x[M], h[M], y[M];
            for (int i = 0; i < M; ++i) {
                alignas(64) float t[W];
                for (int j = 0; j < W; ++j) t[j] = -0.01f * static_cast<float>(i * W + j + task % 7);
                x[i] = loadv(t);
                h[i] = y[i] = splat(0.0f);
            }
            for (int64_t r = 0; r < repeats; ++r) {
                const float bn = 1.0f + 1e-6f * static_cast<float>(r & 15), cn = 0.5f;
                for (int i = 0; i < M; ++i) {
                    h[i] = exp_v(x[i] * 1.5f) * h[i] + x[i] * bn;
                    y[i] += h[i] * cn;
                }
            }
            double s = 0.0;
            for (int i = 0; i < M; ++i) s += hsum(y[i]);
            sums[task] = s;
        }
    });
    double total = 0.0;
    for (double s : sums) total += s;
    return total;
}

// How many distinct intra-op threads run_tasks puts to work on `ntasks` tasks that each take a while: the check
// that the build really runs in parallel (without -fopenmp, at::parallel_for's OpenMP pragma is ignored and
// every task runs on the calling thread).
int64_t threads_used(int64_t ntasks) {
    std::vector<std::atomic<int>> seen(std::max<int64_t>(1, at::get_num_threads()));
    run_tasks(ntasks, [&](auto next) {
        for (int64_t t = next(); t >= 0; t = next()) {
            const int id = at::get_thread_num();
            if (id >= 0 && id < static_cast<int>(seen.size())) seen[id].store(1);
            volatile double x = 0.0;  // a few ms of work, so that one thread cannot take every task alone
            for (int i = 0; i < 2000000; ++i) x = x + 1e-9 * i;
        }
    });
    int64_t used = 0;
    for (auto& v : seen) used += v.load();
    return used;
}

// f applied to x's elements W at a time (x as float32, padded with zeros to whole vectors): the tests' view of the
// kernel's vector functions.
template <class F>
at::Tensor map_lanes(const at::Tensor& x, F f) {
    at::Tensor xc = x.contiguous().to(at::kFloat);
    const int64_t n = xc.numel(), padded = (n + W - 1) / W * W;
    at::Tensor in = at::zeros({padded}, xc.options());
    in.narrow(0, 0, n).copy_(xc.view(-1));
    at::Tensor out = at::empty_like(in);
    const float* xp = in.data_ptr<float>();
    float* op = out.data_ptr<float>();
    for (int64_t i = 0; i < padded; i += W) storev(op + i, f(loadv(xp + i)));
    return out.narrow(0, 0, n).view(x.sizes()).clone();
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
    m.def("scan_fwd", &scan_fwd, "selective scan forward (CPU, float32)");
    m.def("ss2d_fwd_lowrank", &ss2d_fwd_lowrank, "SS2D forward with the dt projection fused (inference, float32)");
    m.def("ss2d_fwd_lowrank_train", &ss2d_fwd_lowrank_train,
          "SS2D forward with the dt projection fused, checkpoints kept (training, float32)");
    m.def("ss2d_bwd_lowrank", &ss2d_bwd_lowrank, "backward of ss2d_fwd_lowrank_train (float32)");
    m.def("ss2d_out_gate", &ss2d_out_gate, "SS2D's LayerNorm(y) * SiLU(z), in place (inference, float32)");
    m.def("threads_used", &threads_used, "distinct intra-op threads that ran tasks (the parallel build check)");
    m.def("scan_bwd", &scan_bwd, "selective scan backward (CPU, float32)");
    m.def("roofline_loop", &roofline_loop, "exp + 3 FMA per element, the scan's per-update floor");
    m.def("exp_fast", [](const at::Tensor& x) { return map_lanes(x, [](vf v) { return exp_v(v); }); },
          "the kernel's exp (for tests)");
    // whether the decays take exp2_v (forward and backward) and the inference forward softplus_fast_v
    m.attr("inference_exp2") = HAVE_EXP2_FAST;
    m.def("exp2_fast",
          [](const at::Tensor& x) {
              const DenormalFlush flush;  // as the scan's tasks run it
              return map_lanes(x, [](vf v) { return exp2_v(v); });
          },
          "the inference forward's 2^x, denormal results flushed to 0 (for tests)");
}
