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
// Work split: one task per (batch, block of W = 16 channels-in-group); a task walks every group in turn, so
// the SS2D sum over directions (y, du) needs no atomics. The 16 channels are the vector lanes; the N states
// of the block (N x 16 floats) stay in L1. exp(delta A) is one vectorisable range reduction + polynomial.
// The forward saves the state entering every chunk of T positions; the backward walks chunks in reverse,
// recomputes the chunk's states and decays from that checkpoint into a small buffer, and runs the adjoint
// recursion g_t = C_t dy_t + a_{t+1} g_{t+1}. dB, dC (shared by a group's channels) are reduced over the
// lanes and written per channel block; dA, dD, dbias per batch element (summed by the caller).
#include <torch/extension.h>
#include <ATen/Parallel.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>

namespace {

constexpr int W = 16;      // lanes: channels per task
constexpr int NMAX = 64;   // largest d_state

// exp(x): x = n ln2 + r, |r| <= ln2 / 2, exp(r) by its degree-6 Taylor polynomial (rel. error ~1.2e-7), 2^n
// by building the exponent bits. Branch-free so that loops over lanes vectorise. Clamped to [-87, 88].
inline float exp_fast(float x) {
    x = std::min(std::max(x, -87.0f), 88.0f);
    const float n = std::floor(x * 1.44269504088896341f + 0.5f);
    float r = std::fma(n, -0.693359375f, x);
    r = std::fma(n, 2.12194440e-4f, r);
    float p = 1.0f / 720.0f;
    p = std::fma(p, r, 1.0f / 120.0f);
    p = std::fma(p, r, 1.0f / 24.0f);
    p = std::fma(p, r, 1.0f / 6.0f);
    p = std::fma(p, r, 0.5f);
    p = std::fma(p, r, 1.0f);
    p = std::fma(p, r, 1.0f);
    int32_t e = (static_cast<int32_t>(n) + 127) << 23;
    float s;
    std::memcpy(&s, &e, sizeof(s));
    return p * s;
}

// softplus(x) = max(x, 0) + log(1 + e), e = exp(-|x|) in (0, 1]; log(1 + e) = 2 atanh(s), s = e / (2 + e)
// in (0, 1/3], by its odd series to s^13 (truncation < 2e-8 relative). Also returns sigmoid(x).
inline float softplus_fast(float x, float* sig) {
    const float e = exp_fast(-std::fabs(x));
    const float s = e / (2.0f + e);
    const float s2 = s * s;
    float p = 1.0f / 13.0f;
    p = std::fma(p, s2, 1.0f / 11.0f);
    p = std::fma(p, s2, 1.0f / 9.0f);
    p = std::fma(p, s2, 1.0f / 7.0f);
    p = std::fma(p, s2, 1.0f / 5.0f);
    p = std::fma(p, s2, 1.0f / 3.0f);
    p = std::fma(p, s2, 1.0f);
    const float inv = 1.0f / (1.0f + e);
    *sig = x >= 0.0f ? inv : e * inv;
    return std::max(x, 0.0f) + 2.0f * s * p;
}

struct Geometry {
    int64_t batch, L, G, Dg, N, Du, H, Wd;
    bool ss2d;
    // spatial position of scan step l in group (direction) g
    inline int64_t pos(int64_t g, int64_t l) const {
        if (!ss2d) return l;
        if (g >= 2) l = L - 1 - l;
        if (g == 0 || g == 2) return l;
        const int64_t i = l % H, j = l / H;  // column-major step l = j H + i
        return i * Wd + j;
    }
};

struct Strides4 {
    int64_t b, l, g, n;
};

inline Strides4 strides4(const at::Tensor& t) { return {t.stride(0), t.stride(1), t.stride(2), t.stride(3)}; }

void check_inputs(const at::Tensor& u, const at::Tensor& delta, const at::Tensor& A, const at::Tensor& B,
                  const at::Tensor& C, const at::Tensor& D, const at::Tensor& bias, const Geometry& geo) {
    for (const at::Tensor* t : {&u, &delta, &A, &B, &C}) {
        TORCH_CHECK(t->device().is_cpu() && t->scalar_type() == at::kFloat, "selective_scan_cpu: float32 CPU tensors expected");
    }
    TORCH_CHECK(u.dim() == 3 && u.is_contiguous(), "selective_scan_cpu: u must be a contiguous (batch, L, Du) tensor");
    TORCH_CHECK(delta.dim() == 3 && delta.is_contiguous(), "selective_scan_cpu: delta must be a contiguous (batch, L, dim) tensor");
    TORCH_CHECK(A.dim() == 2 && A.is_contiguous(), "selective_scan_cpu: A must be a contiguous (dim, N) tensor");
    TORCH_CHECK(B.dim() == 4 && C.dim() == 4, "selective_scan_cpu: B and C must be (batch, L, G, N)");
    TORCH_CHECK(geo.N <= NMAX, "selective_scan_cpu: d_state must be <= ", NMAX);
    TORCH_CHECK(u.size(0) == geo.batch && u.size(1) == geo.L && delta.size(2) == geo.G * geo.Dg, "selective_scan_cpu: shape mismatch");
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

// Per-block constants: A, D, bias in lanes (inactive lanes: A = 0, D = 0, bias = 0).
struct BlockParams {
    alignas(64) float A[NMAX][W];
    alignas(64) float D[W];
    alignas(64) float bias[W];
};

inline void load_params(BlockParams& p, const float* A, const float* D, const float* bias, int64_t c0, int nw, int64_t N) {
    for (int64_t n = 0; n < N; ++n)
        for (int j = 0; j < W; ++j) p.A[n][j] = j < nw ? A[(c0 + j) * N + n] : 0.0f;
    for (int j = 0; j < W; ++j) {
        p.D[j] = (D != nullptr && j < nw) ? D[c0 + j] : 0.0f;
        p.bias[j] = (bias != nullptr && j < nw) ? bias[c0 + j] : 0.0f;
    }
}

// Copy nw <= W floats into lanes, zero-filling the rest. One block copy when full: element-wise stores
// followed by a vector load of the same array stall store-to-load forwarding.
inline void load_lanes(float* dst, const float* src, int nw) {
    if (nw == W) {
        std::memcpy(dst, src, sizeof(float) * W);
    } else {
        std::memset(dst, 0, sizeof(float) * W);
        std::memcpy(dst, src, sizeof(float) * nw);
    }
}

// delta (after bias / softplus), its derivative w.r.t. the raw delta, and u of one step, in lanes.
inline void load_step(const float* delta_row, const float* u_row, const BlockParams& p, int nw, bool softplus,
                      float* dl, float* dsig, float* uu) {
    alignas(64) float raw[W];
    load_lanes(raw, delta_row, nw);
    load_lanes(uu, u_row, nw);
    if (softplus) {
        for (int j = 0; j < W; ++j) {
            float s;
            const float v = softplus_fast(raw[j] + p.bias[j], &s);
            dl[j] = j < nw ? v : 0.0f;  // inactive lanes: no step, no decay
            dsig[j] = s;
        }
    } else {
        for (int j = 0; j < W; ++j) {
            dl[j] = raw[j] + p.bias[j];
            dsig[j] = 1.0f;
        }
    }
}

struct FwdArgs {
    Geometry geo;
    int64_t nblk, nck, chunk;
    bool softplus;
    const float *u, *delta, *A, *B, *C, *D, *bias;
    float *y, *ck;
    Strides4 sB, sC;
};

// Forward tasks [begin, end); NT = d_state known at compile time (the state loop unrolls and the states
// live in registers), or 0 = runtime d_state.
template <int NT>
void fwd_tasks(const FwdArgs& a, int64_t begin, int64_t end) {
    const Geometry& geo = a.geo;
    const int64_t N = NT > 0 ? NT : geo.N, L = geo.L, G = geo.G, Dg = geo.Dg, Du = geo.Du, Dall = G * Dg;
    const int64_t nblk = a.nblk, nck = a.nck, chunk = a.chunk;
    const bool ss2d = geo.ss2d, softplus = a.softplus;
    const Strides4 sB = a.sB, sC = a.sC;
    BlockParams prm;
    alignas(64) float h[NMAX][W];
    alignas(64) float dl[W], dsig[W], uu[W], du[W], yy[W];
    for (int64_t task = begin; task < end; ++task) {
        const int64_t b = task / nblk, blk = task % nblk;
        const int64_t d0 = blk * W;
        const int nw = static_cast<int>(std::min<int64_t>(W, Dg - d0));
        for (int64_t g = 0; g < G; ++g) {
            const int64_t c0 = g * Dg + d0;      // channel of lane 0
            const int64_t uc0 = ss2d ? d0 : c0;  // u / y column of lane 0
            load_params(prm, a.A, a.D, a.bias, c0, nw, N);
            for (int64_t n = 0; n < N; ++n)
                for (int j = 0; j < W; ++j) h[n][j] = 0.0f;
            float* ckg = a.ck + (((b * nblk + blk) * G + g) * nck) * N * W;
            int64_t in_chunk = 0;
            for (int64_t l = 0; l < L; ++l, ++in_chunk) {
                if (in_chunk == chunk) in_chunk = 0;
                if (in_chunk == 0) std::memcpy(ckg + (l / chunk) * N * W, h, sizeof(float) * N * W);
                const int64_t p = geo.pos(g, l);
                load_step(a.delta + (b * L + p) * Dall + c0, a.u + (b * L + p) * Du + uc0, prm, nw, softplus, dl, dsig, uu);
                const float* Bl = a.B + b * sB.b + p * sB.l + g * sB.g;
                const float* Cl = a.C + b * sC.b + p * sC.l + g * sC.g;
                for (int j = 0; j < W; ++j) {
                    du[j] = dl[j] * uu[j];
                    yy[j] = prm.D[j] * uu[j];
                }
#pragma GCC unroll 16
                for (int64_t n = 0; n < N; ++n) {
                    const float bn = Bl[n * sB.n], cn = Cl[n * sC.n];
                    for (int j = 0; j < W; ++j) {
                        const float decay = exp_fast(dl[j] * prm.A[n][j]);
                        const float hn = std::fma(decay, h[n][j], du[j] * bn);
                        h[n][j] = hn;
                        yy[j] = std::fma(cn, hn, yy[j]);
                    }
                }
                float* yrow = a.y + (b * L + p) * Du + uc0;
                if (ss2d) {
                    for (int j = 0; j < nw; ++j) yrow[j] += yy[j];
                } else {
                    for (int j = 0; j < nw; ++j) yrow[j] = yy[j];
                }
            }
        }
    }
}

struct BwdArgs {
    Geometry geo;
    int64_t nblk, nck, chunk;
    bool softplus;
    const float *u, *delta, *A, *B, *C, *D, *bias, *ck, *dy;
    float *du, *ddelta, *dA, *dB, *dC, *dD, *dbias;
    Strides4 sB, sC;
};

// Backward tasks [begin, end) (NT as in fwd_tasks).
template <int NT>
void bwd_tasks(const BwdArgs& a, int64_t begin, int64_t end) {
    const Geometry& geo = a.geo;
    const int64_t N = NT > 0 ? NT : geo.N, L = geo.L, G = geo.G, Dg = geo.Dg, Du = geo.Du, Dall = G * Dg;
    const int64_t nblk = a.nblk, nck = a.nck, chunk = a.chunk;
    const bool ss2d = geo.ss2d, softplus = a.softplus;
    const Strides4 sB = a.sB, sC = a.sC;
    const float *up = a.u, *dp = a.delta, *Ap = a.A, *Bp = a.B, *Cp = a.C, *Dp = a.D, *bp = a.bias, *ckp = a.ck, *dyp = a.dy;
    float *dup = a.du, *ddp = a.ddelta, *dAp = a.dA, *dBpp = a.dB, *dCpp = a.dC, *dDp = a.dD, *dbp = a.dbias;
    BlockParams prm;
    // per chunk: states h_t and decays a_t (T x N x W), steps, sigmoids, inputs (T x W)
    std::vector<float> Hbuf(chunk * N * W), Abuf(chunk * N * W), DLbuf(chunk * W), SGbuf(chunk * W), Ubuf(chunk * W);
    alignas(64) float h[NMAX][W], gn[NMAX][W], dAacc[NMAX][W], pB[NMAX][W], pC[NMAX][W];
    alignas(64) float dsum[W], ssum[W], dyv[W], dd[W], dDacc[W], dbacc[W], tmp[W];
    for (int64_t task = begin; task < end; ++task) {
        const int64_t b = task / nblk, blk = task % nblk;
        const int64_t d0 = blk * W;
        const int nw = static_cast<int>(std::min<int64_t>(W, Dg - d0));
        for (int64_t g = 0; g < G; ++g) {
            const int64_t c0 = g * Dg + d0;
            const int64_t uc0 = ss2d ? d0 : c0;
            load_params(prm, Ap, Dp, bp, c0, nw, N);
            for (int64_t n = 0; n < N; ++n)
                for (int j = 0; j < W; ++j) {
                    gn[n][j] = 0.0f;  // a_{t+1} g_{t+1}, carried backwards
                    dAacc[n][j] = 0.0f;
                }
            for (int j = 0; j < W; ++j) dDacc[j] = dbacc[j] = 0.0f;
            const float* ckg = ckp + (((b * nblk + blk) * G + g) * nck) * N * W;
            for (int64_t k = nck - 1; k >= 0; --k) {
                const int64_t t0 = k * chunk, t1 = std::min(L, t0 + chunk);
                std::memcpy(h, ckg + k * N * W, sizeof(float) * N * W);
                // recompute the chunk's states and decays
                for (int64_t t = t0; t < t1; ++t) {
                    const int64_t p = geo.pos(g, t), s = t - t0;
                    float* dl = &DLbuf[s * W];
                    float* uu = &Ubuf[s * W];
                    load_step(dp + (b * L + p) * Dall + c0, up + (b * L + p) * Du + uc0, prm, nw, softplus, dl, &SGbuf[s * W], uu);
                    const float* Bl = Bp + b * sB.b + p * sB.l + g * sB.g;
                    float* Hs = &Hbuf[s * N * W];
                    float* As = &Abuf[s * N * W];
                    for (int j = 0; j < W; ++j) tmp[j] = dl[j] * uu[j];
#pragma GCC unroll 16
                    for (int64_t n = 0; n < N; ++n) {
                        const float bn = Bl[n * sB.n];
                        for (int j = 0; j < W; ++j) {
                            const float decay = exp_fast(dl[j] * prm.A[n][j]);
                            const float hn = std::fma(decay, h[n][j], tmp[j] * bn);
                            h[n][j] = hn;
                            As[n * W + j] = decay;
                            Hs[n * W + j] = hn;
                        }
                    }
                }
                // adjoint recursion, newest position first
                for (int64_t t = t1 - 1; t >= t0; --t) {
                    const int64_t p = geo.pos(g, t), s = t - t0;
                    const float* dl = &DLbuf[s * W];
                    const float* uu = &Ubuf[s * W];
                    const float* Hs = &Hbuf[s * N * W];
                    const float* As = &Abuf[s * N * W];
                    const float* Bl = Bp + b * sB.b + p * sB.l + g * sB.g;
                    const float* Cl = Cp + b * sC.b + p * sC.l + g * sC.g;
                    const float* dyrow = dyp + (b * L + p) * Du + uc0;
                    load_lanes(dyv, dyrow, nw);
                    for (int j = 0; j < W; ++j) {
                        dsum[j] = 0.0f;  // dL/d(delta_t)
                        ssum[j] = 0.0f;  // sum_n g_n B_n
                        tmp[j] = dl[j] * uu[j];
                    }
                    float* dBrow = dBpp + (((blk * geo.batch + b) * L + p) * G + g) * N;
                    float* dCrow = dCpp + (((blk * geo.batch + b) * L + p) * G + g) * N;
#pragma GCC unroll 16
                    for (int64_t n = 0; n < N; ++n) {
                        const float bn = Bl[n * sB.n], cn = Cl[n * sC.n];
                        float* gnn = gn[n];
                        float* dAn = dAacc[n];
                        const float* An = prm.A[n];
                        const float* Hn = Hs + n * W;
                        const float* Asn = As + n * W;
                        for (int j = 0; j < W; ++j) {
                            const float gt = std::fma(cn, dyv[j], gnn[j]);
                            const float hn = Hn[j];
                            const float ah = std::fma(-tmp[j], bn, hn);  // a_t h_{t-1} = h_t - delta u B
                            const float gah = gt * ah;
                            dsum[j] = std::fma(An[j], gah, dsum[j]);
                            dAn[j] = std::fma(dl[j], gah, dAn[j]);
                            ssum[j] = std::fma(gt, bn, ssum[j]);
                            pB[n][j] = gt * tmp[j];
                            pC[n][j] = hn * dyv[j];
                            gnn[j] = Asn[j] * gt;
                        }
                    }
                    // dB_t[n], dC_t[n]: sums over the lanes (a transpose-free tree over the N x W products)
                    for (int64_t n = 0; n < N; ++n) {
                        float sb = 0.0f, sc = 0.0f;
                        for (int j = 0; j < W; ++j) {
                            sb += pB[n][j];
                            sc += pC[n][j];
                        }
                        dBrow[n] = sb;
                        dCrow[n] = sc;
                    }
                    const float* sg = &SGbuf[s * W];
                    for (int j = 0; j < W; ++j) {
                        // d delta_t = sum_n g_n (A_n a_n h_{t-1,n} + u B_n); through softplus: * sigmoid
                        const float ddl = std::fma(uu[j], ssum[j], dsum[j]) * sg[j];
                        dd[j] = ddl;
                        dbacc[j] += ddl;
                        dDacc[j] = std::fma(dyv[j], uu[j], dDacc[j]);
                        tmp[j] = std::fma(dl[j], ssum[j], prm.D[j] * dyv[j]);  // dL/du_t
                    }
                    float* ddrow = ddp + (b * L + p) * Dall + c0;
                    for (int j = 0; j < nw; ++j) ddrow[j] = dd[j];
                    float* durow = dup + (b * L + p) * Du + uc0;
                    if (ss2d) {
                        for (int j = 0; j < nw; ++j) durow[j] += tmp[j];
                    } else {
                        for (int j = 0; j < nw; ++j) durow[j] = tmp[j];
                    }
                }
            }
            for (int j = 0; j < nw; ++j) {
                for (int64_t n = 0; n < N; ++n) dAp[(b * Dall + c0 + j) * N + n] = dAacc[n][j];
                dDp[b * Dall + c0 + j] = dDacc[j];
                dbp[b * Dall + c0 + j] = dbacc[j];
            }
        }
    }
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
    TORCH_CHECK(chunk >= 1, "selective_scan_cpu: chunk must be >= 1");
    const int64_t nblk = (geo.Dg + W - 1) / W;
    const int64_t nck = (geo.L + chunk - 1) / chunk;
    at::Tensor y = ss2d ? at::zeros_like(u) : at::empty_like(u);
    // state entering each chunk: (batch, nblk, G, nck, N, W)
    at::Tensor ck = at::empty({geo.batch, nblk, geo.G, nck, geo.N, W}, u.options());
    const float* up = u.data_ptr<float>();
    const float* dp = delta.data_ptr<float>();
    const float* Ap = A.data_ptr<float>();
    const float* Bp = B.data_ptr<float>();
    const float* Cp = C.data_ptr<float>();
    const float* Dp = D.defined() ? D.data_ptr<float>() : nullptr;
    const float* bp = bias.defined() ? bias.data_ptr<float>() : nullptr;
    float* yp = y.data_ptr<float>();
    float* ckp = ck.data_ptr<float>();
    const Strides4 sB = strides4(B), sC = strides4(C);
    const int64_t N = geo.N, L = geo.L, G = geo.G, Dg = geo.Dg, Du = geo.Du, Dall = G * Dg;

    const FwdArgs args{geo, nblk, nck, chunk, softplus, up, dp, Ap, Bp, Cp, Dp, bp, yp, ckp, sB, sC};
    at::parallel_for(0, geo.batch * nblk, 1, [&](int64_t begin, int64_t end) {
        if (geo.N == 16) {
            fwd_tasks<16>(args, begin, end);
        } else {
            fwd_tasks<0>(args, begin, end);
        }
    });
    return {y, ck};
}

std::vector<at::Tensor> scan_bwd(const at::Tensor& u, const at::Tensor& delta, const at::Tensor& A, const at::Tensor& B,
                                 const at::Tensor& C, const c10::optional<at::Tensor>& D_opt,
                                 const c10::optional<at::Tensor>& bias_opt, bool softplus, bool ss2d, int64_t H,
                                 int64_t Wd, int64_t chunk, const at::Tensor& ck, const at::Tensor& dy_in) {
    const at::Tensor D = D_opt.has_value() ? *D_opt : at::Tensor();
    const at::Tensor bias = bias_opt.has_value() ? *bias_opt : at::Tensor();
    const Geometry geo = make_geometry(u, A, B, ss2d, H, Wd);
    check_inputs(u, delta, A, B, C, D, bias, geo);
    const at::Tensor dy = dy_in.contiguous();
    TORCH_CHECK(dy.sizes() == u.sizes() && dy.scalar_type() == at::kFloat, "selective_scan_cpu: dy must have y's shape");
    const int64_t nblk = (geo.Dg + W - 1) / W;
    const int64_t nck = (geo.L + chunk - 1) / chunk;
    TORCH_CHECK(ck.is_contiguous() && ck.numel() == geo.batch * nblk * geo.G * nck * geo.N * W, "selective_scan_cpu: bad checkpoints");
    const int64_t N = geo.N, L = geo.L, G = geo.G, Dg = geo.Dg, Du = geo.Du, Dall = G * Dg;

    at::Tensor du_out = ss2d ? at::zeros_like(u) : at::empty_like(u);
    at::Tensor ddelta = at::empty_like(delta);
    at::Tensor dA = at::empty({geo.batch, Dall, N}, u.options());
    at::Tensor dBp = at::empty({nblk, geo.batch, L, G, N}, u.options());
    at::Tensor dCp = at::empty({nblk, geo.batch, L, G, N}, u.options());
    at::Tensor dD = at::empty({geo.batch, Dall}, u.options());
    at::Tensor dbias = at::empty({geo.batch, Dall}, u.options());

    const float* up = u.data_ptr<float>();
    const float* dp = delta.data_ptr<float>();
    const float* Ap = A.data_ptr<float>();
    const float* Bp = B.data_ptr<float>();
    const float* Cp = C.data_ptr<float>();
    const float* Dp = D.defined() ? D.data_ptr<float>() : nullptr;
    const float* bp = bias.defined() ? bias.data_ptr<float>() : nullptr;
    const float* ckp = ck.data_ptr<float>();
    const float* dyp = dy.data_ptr<float>();
    float* dup = du_out.data_ptr<float>();
    float* ddp = ddelta.data_ptr<float>();
    float* dAp = dA.data_ptr<float>();
    float* dBpp = dBp.data_ptr<float>();
    float* dCpp = dCp.data_ptr<float>();
    float* dDp = dD.data_ptr<float>();
    float* dbp = dbias.data_ptr<float>();
    const Strides4 sB = strides4(B), sC = strides4(C);

    const BwdArgs args{geo, nblk, nck, chunk, softplus, up, dp, Ap, Bp, Cp, Dp, bp, ckp, dyp,
                       dup, ddp, dAp, dBpp, dCpp, dDp, dbp, sB, sC};
    at::parallel_for(0, geo.batch * nblk, 1, [&](int64_t begin, int64_t end) {
        if (geo.N == 16) {
            bwd_tasks<16>(args, begin, end);
        } else {
            bwd_tasks<0>(args, begin, end);
        }
    });
    return {du_out, ddelta, dA.sum(0), dBp.sum(0), dCp.sum(0), dD.sum(0), dbias.sum(0)};
}

// The roofline of the scan: a plain vectorised loop doing what one state update costs at least, one exp and
// three multiply-adds per element (decay argument, state update, readout), on L1-resident lanes. ``tasks``
// independent tasks of 256 elements x ``repeats`` sweeps (tasks x 256 x repeats updates in all); returns a
// checksum so that the work cannot be optimised away.
double roofline_loop(int64_t tasks, int64_t repeats) {
    std::vector<double> sums(tasks, 0.0);
    at::parallel_for(0, tasks, 1, [&](int64_t begin, int64_t end) {
        constexpr int M = 256;
        alignas(64) float x[M], h[M], y[M];
        for (int64_t task = begin; task < end; ++task) {
            for (int i = 0; i < M; ++i) {
                x[i] = -0.01f * static_cast<float>(i + task % 7);
                h[i] = y[i] = 0.0f;
            }
            for (int64_t r = 0; r < repeats; ++r) {
                const float bn = 1.0f + 1e-6f * static_cast<float>(r & 15), cn = 0.5f;
                for (int i = 0; i < M; ++i) {
                    const float a = exp_fast(x[i] * 1.5f);
                    h[i] = std::fma(a, h[i], x[i] * bn);
                    y[i] = std::fma(cn, h[i], y[i]);
                }
            }
            double s = 0.0;
            for (int i = 0; i < M; ++i) s += y[i];
            sums[task] = s;
        }
    });
    double total = 0.0;
    for (double s : sums) total += s;
    return total;
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
    m.def("scan_fwd", &scan_fwd, "selective scan forward (CPU, float32)");
    m.def("scan_bwd", &scan_bwd, "selective scan backward (CPU, float32)");
    m.def("roofline_loop", &roofline_loop, "exp + 3 FMA per element, the scan's per-update floor");
    m.def("exp_fast", [](const at::Tensor& x) {
        at::Tensor xc = x.contiguous().to(at::kFloat);
        at::Tensor out = at::empty_like(xc);
        const float* xp = xc.data_ptr<float>();
        float* op = out.data_ptr<float>();
        for (int64_t i = 0; i < xc.numel(); ++i) op[i] = exp_fast(xp[i]);
        return out;
    }, "the kernel's exp (for tests)");
}
