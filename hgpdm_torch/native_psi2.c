/* Fused psi2 contractions for hgpdm_torch.native (AVX-512, float64).

   Compiled on first use by hgpdm_torch/native.py with the machine's C compiler and
   -O3 -march=native; loaded with ctypes. Nine entry points:

   - hgpdm_exp_f64: exp of an array in place, within 2 ulp (see exp8);
   - hgpdm_psi2_groups_f64: for each stream s of the shared transition GP,
       T[s, u, v]     = sum_{l, m} psi2[s, (u, l), (v, m)] kinv[(u, l), (v, m)]   (groups u, v)
       out[s, (a, b), k] = sum_{u, v} phi[k, u] phi[k, v] S[s, u, (a, b), v]      (a <= b), with
       S[s, u, (a, b), v] = sum_{l, m} beta[(u, l), a] psi2[s, (u, l), (v, m)] beta[(v, m), b],
       and in the row after the pairs the trace out[s, P, k] = sum_{u, v} phi[k, u] phi[k, v]
       T[s, u, v] (tr(K^-1 psi2) of value k), contracted as each row of T is complete, and
       psi1[s, i] on the way,
     psi2[s] = exp(d_i^T H d_j + r_i + s_j) (exponent) evaluated eight columns of one group's
     rows at a time in registers and never stored (its factors, O(N D) per stream, are built
     from the stream's quadratic form in the work space): one pass over the N x N block
     instead of the exponential, the weighted sums and the K^-1 product each reading and
     writing it; S of one group is contracted with phi while it is in the L1 cache;
   - hgpdm_rbf_forms_f64: each stream's quadratic forms of psi2 and psi1 (rbf_forms);
   - hgpdm_predictive_step_f64: the online filter's whole predictive step per stream, the
     contraction fused with the transition moments, measurement update, belief step and
     mixture that consume it (step_tail);
   - hgpdm_mcp_shared_f64 and hgpdm_mcp_particles_f64: Monte-Carlo planning's particles of one
     belief, what they share once, then their draws and the same step (particle_block);
   - hgpdm_rbf_values_f64: the planner's default values of beliefs (belief vectors, radial
     basis features, linear values; block_values);
   - hgpdm_mcp_values_f64: the particles' step and their values in one pass, each particle's
     best value the only output;
   - hgpdm_draws_f64: torch.multinomial's draws and torch.randn's normals (Box-Muller,
     vectorised log and sincos) from torch's own uniforms.

   Layout: points (training inputs) in group order (u, l), N = U L (padding points have zero
   weights). The columns are in the order (m, v), v padded to Up (a multiple of 8), Np = L Up:
   column m Up + v is point (v, m); padding columns have zero kinv and betac, so they add
   nothing. */
#include <immintrin.h>
#include <math.h>
#include <stdint.h>

#if !defined(__AVX512F__) || !defined(__AVX512DQ__)
#error "hgpdm_torch.native needs AVX-512F and DQ (compiled with -march=native on such a CPU)"
#endif

#define W 8 /* doubles per AVX-512 register */
#define LANE_MASK(n) ((__mmask8)((1u << (n)) - 1u)) /* the low n < W lanes */
#define TAIL_MASK(n, j) ((n) - (j) < W ? LANE_MASK((n) - (j)) : (__mmask8)0xFF) /* j .. n - 1 */

/* Each entry point runs with subnormal results and operands flushed to zero (FTZ | DAZ) and
   restores the caller's MXCSR: psi2 of far-apart points, a belief's probabilities of values far
   from the data and the features of far centres underflow, and arithmetic on subnormals takes
   microcode assists (up to ~100 times slower per operation); each changes a sum by less than
   2.3e-308. */
static inline unsigned int ftz_begin(void) {
    const unsigned int csr = _mm_getcsr();
    _mm_setcsr(csr | 0x8040);
    return csr;
}
#define MAX_D 8
#define INLINE static inline __attribute__((always_inline))
/* CALL(DD) with DD the compile-time constant equal to D (the kernels' loops over D unroll);
   status 0, or 1 (nothing run) for D outside 1..MAX_D */
#define FOR_D(D, CALL, status)                                                  \
    switch (D) {                                                                \
    case 1: CALL(1); status = 0; break;                                         \
    case 2: CALL(2); status = 0; break;                                         \
    case 3: CALL(3); status = 0; break;                                         \
    case 4: CALL(4); status = 0; break;                                         \
    case 5: CALL(5); status = 0; break;                                         \
    case 6: CALL(6); status = 0; break;                                         \
    case 7: CALL(7); status = 0; break;                                         \
    case 8: CALL(8); status = 0; break;                                         \
    default: status = 1; break;                                                 \
    }

/* 2^(j/16), j = 0..15, each the double nearest the exact value (checked at 200 bits). */
static const double EXP2_16TH[16] = {
    0x1.0000000000000p+0, 0x1.0b5586cf9890fp+0, 0x1.172b83c7d517bp+0, 0x1.2387a6e756238p+0,
    0x1.306fe0a31b715p+0, 0x1.3dea64c123422p+0, 0x1.4bfdad5362a27p+0, 0x1.5ab07dd485429p+0,
    0x1.6a09e667f3bcdp+0, 0x1.7a11473eb0187p+0, 0x1.8ace5422aa0dbp+0, 0x1.9c49182a3f090p+0,
    0x1.ae89f995ad3adp+0, 0x1.c199bdd85529cp+0, 0x1.d5818dcfba487p+0, 0x1.ea4afa2a490dap+0};

/* exp of 8 lanes. x = (16 q + j) ln2 / 16 + r with |r| <= ln2 / 32: exp(x) = 2^q 2^(j/16) e^r.
   k = 16 q + j is rounded by the 1.5 * 2^52 shift (its low bits index the table); r is
   x - k ln2/16 with ln2/16 in two parts (the first of 40 bits), each product fused; e^r by its
   degree-7 Taylor polynomial (truncation below 1.2e-18 relative); scalef applies 2^q with
   IEEE overflow to inf and gradual underflow. Inputs are clamped to [-746, 710] first, beyond
   which exp is 0 or inf in float64; NaN stays NaN (max/min return their second operand). */
INLINE __m512d exp8(__m512d x) {
    const __m512d shift = _mm512_set1_pd(0x1.8p52);
    x = _mm512_max_pd(_mm512_set1_pd(-746.0), x);
    x = _mm512_min_pd(_mm512_set1_pd(710.0), x);
    __m512d kd = _mm512_fmadd_pd(x, _mm512_set1_pd(0x1.71547652b82fep+4), shift);
    const __m512i idx = _mm512_castpd_si512(kd);
    kd = _mm512_sub_pd(kd, shift);
    __m512d r = _mm512_fnmadd_pd(kd, _mm512_set1_pd(0x1.62e42fefa2000p-5), x);
    r = _mm512_fnmadd_pd(kd, _mm512_set1_pd(0x1.9ef35793c7673p-45), r);
    __m512d p = _mm512_set1_pd(1.0 / 5040.0);
    p = _mm512_fmadd_pd(p, r, _mm512_set1_pd(1.0 / 720.0));
    p = _mm512_fmadd_pd(p, r, _mm512_set1_pd(1.0 / 120.0));
    p = _mm512_fmadd_pd(p, r, _mm512_set1_pd(1.0 / 24.0));
    p = _mm512_fmadd_pd(p, r, _mm512_set1_pd(1.0 / 6.0));
    p = _mm512_fmadd_pd(p, r, _mm512_set1_pd(0.5));
    p = _mm512_fmadd_pd(p, r, _mm512_set1_pd(1.0));
    p = _mm512_fmadd_pd(p, r, _mm512_set1_pd(1.0));
    const __m512d t = _mm512_permutex2var_pd(_mm512_loadu_pd(EXP2_16TH), idx,
                                             _mm512_loadu_pd(EXP2_16TH + 8));
    const __m512d q = _mm512_roundscale_pd(_mm512_mul_pd(kd, _mm512_set1_pd(1.0 / 16.0)),
                                           _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC);
    return _mm512_scalef_pd(_mm512_mul_pd(t, p), q);
}

void hgpdm_exp_f64(int64_t n, double *x) {
    int64_t j = 0;
    for (; j + W <= n; j += W) _mm512_storeu_pd(x + j, exp8(_mm512_loadu_pd(x + j)));
    if (j < n) {
        const __mmask8 k = LANE_MASK(n - j);
        _mm512_mask_storeu_pd(x + j, k, exp8(_mm512_maskz_loadu_pd(k, x + j)));
    }
}

/* ---- Torch's categorical and normal draws (hgpdm_torch.native.categorical_normal) ---- */

/* log of 8 lanes of positive normal x: x = 2^k m with m in [sqrt(1/2), sqrt(2)) (getexp and
   getmant, then halved where above sqrt(2)), f = m - 1, s = f / (2 + f) and
   log x = k ln2 + f - (f^2 / 2 - s (f^2 / 2 + R(s^2))), R the degree-14 even minimax
   polynomial of fdlibm's e_log.c (error below 2^-58.45 on |s| < 0.1716); ln2 in two parts,
   the first of 32 bits (k ln2_hi exact for |k| < 2^20). Within 1 ulp (test_native). */
INLINE __m512d log8(__m512d x) {
    __m512d m = _mm512_getmant_pd(x, _MM_MANT_NORM_1_2, _MM_MANT_SIGN_zero);
    __m512d k = _mm512_getexp_pd(x);
    const __mmask8 big = _mm512_cmp_pd_mask(m, _mm512_set1_pd(0x1.6a09e667f3bcdp+0), _CMP_GT_OQ);
    m = _mm512_mask_mul_pd(m, big, m, _mm512_set1_pd(0.5));
    k = _mm512_mask_add_pd(k, big, k, _mm512_set1_pd(1.0));
    const __m512d f = _mm512_sub_pd(m, _mm512_set1_pd(1.0));
    const __m512d s = _mm512_div_pd(f, _mm512_add_pd(_mm512_set1_pd(2.0), f));
    const __m512d z = _mm512_mul_pd(s, s), w = _mm512_mul_pd(z, z);
    __m512d t1 = _mm512_fmadd_pd(w, _mm512_set1_pd(1.531383769920937332e-01),
                                 _mm512_set1_pd(2.222219843214978396e-01));
    t1 = _mm512_mul_pd(w, _mm512_fmadd_pd(w, t1, _mm512_set1_pd(3.999999999940941908e-01)));
    __m512d t2 = _mm512_fmadd_pd(w, _mm512_set1_pd(1.479819860511658591e-01),
                                 _mm512_set1_pd(1.818357216161805012e-01));
    t2 = _mm512_fmadd_pd(w, t2, _mm512_set1_pd(2.857142874366239149e-01));
    t2 = _mm512_mul_pd(z, _mm512_fmadd_pd(w, t2, _mm512_set1_pd(6.666666666666735130e-01)));
    const __m512d R = _mm512_add_pd(t2, t1);
    const __m512d hfsq = _mm512_mul_pd(_mm512_set1_pd(0.5), _mm512_mul_pd(f, f));
    const __m512d klo = _mm512_mul_pd(k, _mm512_set1_pd(1.90821492927058770002e-10));
    const __m512d inner = _mm512_fmadd_pd(s, _mm512_add_pd(hfsq, R), klo);
    return _mm512_fmsub_pd(k, _mm512_set1_pd(6.93147180369123816490e-01),
                           _mm512_sub_pd(_mm512_sub_pd(hfsq, inner), f));
}

/* sin and cos of 8 lanes of x in [0, 2 pi]: x = n pi/2 + r (n = round(x 2/pi); pi/2 in two
   parts, each product fused, |r| <= pi/4 + 2^-50), the polynomials of fdlibm's k_sin.c and
   k_cos.c on r (degree 13 and 14), and the quadrant's swap and signs. Within 1 ulp
   (test_native). */
INLINE void sincos8(__m512d x, __m512d *sin_out, __m512d *cos_out) {
    const __m512d n = _mm512_roundscale_pd(_mm512_mul_pd(x, _mm512_set1_pd(0x1.45f306dc9c883p-1)),
                                           _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
    __m512d r = _mm512_fnmadd_pd(n, _mm512_set1_pd(0x1.921fb54442d18p+0), x);
    r = _mm512_fnmadd_pd(n, _mm512_set1_pd(0x1.1a62633145c07p-54), r);
    const __m512d z = _mm512_mul_pd(r, r), one = _mm512_set1_pd(1.0);
    __m512d p = _mm512_fmadd_pd(z, _mm512_set1_pd(1.58969099521155010221e-10),
                                _mm512_set1_pd(-2.50507602534068634195e-08));
    p = _mm512_fmadd_pd(z, p, _mm512_set1_pd(2.75573137070700676789e-06));
    p = _mm512_fmadd_pd(z, p, _mm512_set1_pd(-1.98412698298579493134e-04));
    p = _mm512_fmadd_pd(z, p, _mm512_set1_pd(8.33333333332248946124e-03));
    p = _mm512_fmadd_pd(z, p, _mm512_set1_pd(-1.66666666666666324348e-01));
    const __m512d sr = _mm512_fmadd_pd(_mm512_mul_pd(z, r), p, r); /* sin r */
    __m512d q = _mm512_fmadd_pd(z, _mm512_set1_pd(-1.13596475577881948265e-11),
                                _mm512_set1_pd(2.08757232129817482790e-09));
    q = _mm512_fmadd_pd(z, q, _mm512_set1_pd(-2.75573143513906633035e-07));
    q = _mm512_fmadd_pd(z, q, _mm512_set1_pd(2.48015872894767294178e-05));
    q = _mm512_fmadd_pd(z, q, _mm512_set1_pd(-1.38888888888741095749e-03));
    q = _mm512_mul_pd(z, _mm512_fmadd_pd(z, q, _mm512_set1_pd(4.16666666666666019037e-02)));
    const __m512d hz = _mm512_mul_pd(_mm512_set1_pd(0.5), z), w = _mm512_sub_pd(one, hz);
    /* cos r = w + ((1 - w) - hz + z q): 1 - hz's rounding error recovered */
    const __m512d cr = _mm512_add_pd(
        w, _mm512_fmadd_pd(z, q, _mm512_sub_pd(_mm512_sub_pd(one, w), hz)));
    const __m512i quad = _mm512_and_epi64(_mm512_cvtpd_epi64(n), _mm512_set1_epi64(3));
    const __mmask8 swap = _mm512_test_epi64_mask(quad, _mm512_set1_epi64(1));
    const __mmask8 neg_sin = _mm512_test_epi64_mask(quad, _mm512_set1_epi64(2));
    const __mmask8 neg_cos = _mm512_test_epi64_mask(
        _mm512_add_epi64(quad, _mm512_set1_epi64(1)), _mm512_set1_epi64(2));
    const __m512d sv = _mm512_mask_blend_pd(swap, sr, cr), cv = _mm512_mask_blend_pd(swap, cr, sr);
    const __m512d zero = _mm512_setzero_pd();
    *sin_out = _mm512_mask_sub_pd(sv, neg_sin, zero, sv);
    *cos_out = _mm512_mask_sub_pd(cv, neg_cos, zero, cv);
}

/* Sixteen standard normal draws out[0..15] from sixteen uniforms u in [0, 1): for j < 8,
   with rho = sqrt(-2 log(1 - u[j])) and theta = 2 pi u[j + 8], out[j] = rho cos theta and
   out[j + 8] = rho sin theta (torch's normal_fill_16). */
INLINE void normal16(const double *u, double *out) {
    const __m512d u1 = _mm512_sub_pd(_mm512_set1_pd(1.0), _mm512_loadu_pd(u));
    const __m512d theta = _mm512_mul_pd(_mm512_set1_pd(2.0 * 0x1.921fb54442d18p+1),
                                        _mm512_loadu_pd(u + 8));
    const __m512d rho = _mm512_sqrt_pd(_mm512_mul_pd(_mm512_set1_pd(-2.0), log8(u1)));
    __m512d sn, cs;
    sincos8(theta, &sn, &cs);
    _mm512_storeu_pd(out, _mm512_mul_pd(rho, cs));
    _mm512_storeu_pd(out + 8, _mm512_mul_pd(rho, sn));
}

/* n >= 16 standard normal draws out [n] from the uniforms u [n + (16 if n % 16 else 0)] in
   [0, 1), as torch.randn forms them (float64, n >= 16): blocks of sixteen (normal16), and where
   n is not a multiple of 16 the last sixteen draws again from the sixteen uniforms after the
   n. */
static void normals(int64_t n, const double *u, double *out) {
    for (int64_t i = 0; i + 16 <= n; i += 16) normal16(u + i, out + i);
    if (n % 16) normal16(u + n, out + n - 16);
}

/* I categorical draws g [I] from prob [K] as torch.multinomial draws them with replacement in
   float64 (the running sum's cumulative distribution over its total, its last entry set to 1;
   each draw the first entry not below its uniform, by bisection), then n >= 16 standard normal
   draws eps [n] (normals), from the uniforms u [I + n + (16 if n % 16 else 0)] that
   torch would draw for the two in that order. cdf [K] is work. Returns 0; 1 where prob has a
   negative or non-finite entry or no positive total (nothing written); 2 for n < 16. */
int hgpdm_draws_f64(int64_t I, int64_t K, const double *prob, int64_t n, const double *u,
                    int64_t *g, double *eps, double *cdf) {
    if (n < 16) return 2;
    double total = 0.0;
    for (int64_t k = 0; k < K; ++k) {
        if (!(prob[k] >= 0.0) || !isfinite(prob[k])) return 1;
        total += prob[k];
        cdf[k] = total;
    }
    if (!(total > 0.0)) return 1;
    for (int64_t k = 0; k < K; ++k) cdf[k] /= total;
    cdf[K - 1] = 1.0;
    for (int64_t i = 0; i < I; ++i) {
        int64_t lo = 0, hi = K;
        while (hi > lo) {
            const int64_t mid = lo + (hi - lo) / 2;
            if (cdf[mid] < u[i])
                lo = mid + 1;
            else
                hi = mid;
        }
        g[i] = lo;
    }
    normals(n, u + I, eps);
    return 0;
}

/* The L rows of group u against all Np columns: acc[j] = sum_l psi2 kinv and
   prow[a, j] = sum_l beta[(u, l), a] psi2, eight columns at a time in registers. */
INLINE void group_rows(const int D, int64_t L, int64_t C, int64_t Np, const double *lu,
                       const double *right, const double *bu, const double *ku, double *prow,
                       double *acc) {
    for (int64_t j = 0; j < Np; j += W) {
        __m512d a = _mm512_setzero_pd(), P[MAX_D];
        for (int d = 0; d < D; ++d) P[d] = _mm512_setzero_pd();
        for (int64_t l = 0; l < L; ++l) {
            const double *li = lu + l * C;
            __m512d e = _mm512_mul_pd(_mm512_set1_pd(li[0]), _mm512_loadu_pd(right + j));
            for (int c = 1; c < D; ++c)
                e = _mm512_fmadd_pd(_mm512_set1_pd(li[c]), _mm512_loadu_pd(right + c * Np + j), e);
            /* r_i, then s_j: additions (not products by 1), off the FMA units that the
               exponential keeps busy */
            e = _mm512_add_pd(e, _mm512_set1_pd(li[D]));
            e = exp8(_mm512_add_pd(e, _mm512_loadu_pd(right + D * Np + j)));
            a = _mm512_fmadd_pd(e, _mm512_loadu_pd(ku + l * Np + j), a);
            for (int d = 0; d < D; ++d)
                P[d] = _mm512_fmadd_pd(_mm512_set1_pd(bu[l * D + d]), e, P[d]);
        }
        _mm512_storeu_pd(acc + j, a);
        for (int d = 0; d < D; ++d) _mm512_storeu_pd(prow + d * Np + j, P[d]);
    }
}

/* Group u's sums over the L column blocks: Tu[v] = sum_m acc[m Up + v] and, for each pair
   a <= b, Su[pair, v] = sum_m prow[a, m Up + v] betac[b, m Up + v]. */
INLINE void group_sums(const int D, int64_t L, int64_t Up, const double *acc, const double *prow,
                       const double *betac, double *Tu, double *Su) {
    const int64_t Np = L * Up;
    for (int64_t v = 0; v < Up; v += W) {
        __m512d t = _mm512_setzero_pd();
        for (int64_t m = 0; m < L; ++m) t = _mm512_add_pd(t, _mm512_loadu_pd(acc + m * Up + v));
        _mm512_storeu_pd(Tu + v, t);
    }
    int64_t pair = 0;
    for (int a = 0; a < D; ++a)
        for (int b = a; b < D; ++b, ++pair)
            for (int64_t v = 0; v < Up; v += W) {
                __m512d s = _mm512_setzero_pd();
                for (int64_t m = 0; m < L; ++m)
                    s = _mm512_fmadd_pd(_mm512_loadu_pd(prow + a * Np + m * Up + v),
                                        _mm512_loadu_pd(betac + b * Np + m * Up + v), s);
                _mm512_storeu_pd(Su + pair * Up + v, s);
            }
}

/* out[p, k] += phiu[k] sum_v Su[p, v] phiT[v, k] for PB rows p and KV vectors of k: a small
   matrix product whose PB x KV accumulators stay in registers. */
INLINE void contract_block(const int PB, const int KV, int64_t Up, int64_t Kp, const double *Su,
                           const double *phiT, const double *phiu, double *out) {
    __m512d acc[5][4], f[4];
    for (int p = 0; p < PB; ++p)
        for (int q = 0; q < KV; ++q) acc[p][q] = _mm512_setzero_pd();
    for (int64_t v = 0; v < Up; ++v) {
        for (int q = 0; q < KV; ++q) f[q] = _mm512_loadu_pd(phiT + v * Kp + q * W);
        for (int p = 0; p < PB; ++p) {
            const __m512d sv = _mm512_set1_pd(Su[p * Up + v]);
            for (int q = 0; q < KV; ++q) acc[p][q] = _mm512_fmadd_pd(sv, f[q], acc[p][q]);
        }
    }
    for (int p = 0; p < PB; ++p)
        for (int q = 0; q < KV; ++q) {
            double *o = out + p * Kp + q * W;
            _mm512_storeu_pd(o, _mm512_fmadd_pd(acc[p][q], _mm512_loadu_pd(phiu + q * W),
                                                _mm512_loadu_pd(o)));
        }
}

#define BLOCK_CASE(PB, KV)                                                \
    case (PB) * 8 + (KV):                                                 \
        contract_block(PB, KV, Up, Kp, Su + p0 * Up, phiT + k0, phiu + k0, \
                       out + p0 * Kp + k0);                               \
        break;
#define BLOCK_CASES(PB) BLOCK_CASE(PB, 1) BLOCK_CASE(PB, 2) BLOCK_CASE(PB, 3) BLOCK_CASE(PB, 4)

/* out [P, Kp] += phi over both groups of Su [P, Up] (phiT [Up, Kp]: phi[k, v], zero rows at
   padding v; phiu [Kp]: phi[k, u]): the values k < Kv (a multiple of 8) in blocks of 5 pairs x
   32 values, and the Kd values from Kv as dot products over v, eight v at a time (phiR [Kd, Up]:
   those columns of phiT transposed), where a vector of values would hold few of them. */
static void contract(int64_t P, int64_t Up, int64_t Kp, int64_t Kv, int64_t Kd,
                     const double *phiR, const double *Su, const double *phiT,
                     const double *phiu, double *out) {
    for (int64_t p0 = 0; p0 < P; p0 += 5)
        for (int64_t k0 = 0; k0 < Kv; k0 += 4 * W) {
            const int pb = P - p0 < 5 ? (int)(P - p0) : 5;
            const int kv = (Kv - k0) / W < 4 ? (int)((Kv - k0) / W) : 4;
            switch (pb * 8 + kv) {
                BLOCK_CASES(1) BLOCK_CASES(2) BLOCK_CASES(3) BLOCK_CASES(4) BLOCK_CASES(5)
            }
        }
    for (int64_t r = 0; r < Kd; ++r)
        for (int64_t p = 0; p < P; ++p) {
            __m512d t = _mm512_setzero_pd();
            for (int64_t v = 0; v < Up; v += W)
                t = _mm512_fmadd_pd(_mm512_loadu_pd(Su + p * Up + v),
                                    _mm512_loadu_pd(phiR + r * Up + v), t);
            out[p * Kp + Kv + r] += phiu[Kv + r] * _mm512_reduce_add_pd(t);
        }
}

/* The exponent of psi2 for one stream, d_i^T H d_j + r_i + s_j, as the factors left [N, C]
   and right [C, Np] (C = D + 1; group_rows forms the product and adds the last entries), and
   the log of psi1 [N], from the quadratic forms of hgpdm_torch.expectations
   (rbf_psi2_quadratic, rbf_psi1_quadratic): with d = x - mu, left_i = [d_i^T H, r_i = d_i^T Ma
   d_i + c + lp_i], right_j = [d_j; s_j = d_j^T Mb d_j + lp_j] for column j's point cols[j], and
   p1_i = d_i^T P d_i + c1 + lp_i; lp the log phase factors, or none. O((N + Np) D^2), in the
   work space: no O(N D) tensor per stream leaves the kernel. */
INLINE void exponent(const int D, int64_t N, int64_t Np, const double *X, const int64_t *cols,
                     const double *mu, const double *Q, const double *c, const double *lp,
                     double *left, double *right, double *p1) {
    const int C = D + 1;
    const double *H = Q, *Ma = Q + D * D, *Mb = Q + 2 * D * D, *P = Q + 3 * D * D;
    double d[MAX_D];
    for (int64_t i = 0; i < N; ++i) {
        for (int a = 0; a < D; ++a) d[a] = X[i * D + a] - mu[a];
        const double phase = lp ? lp[i] : 0.0;
        double row = c[0] + phase, one = c[1] + phase;
        for (int a = 0; a < D; ++a) {
            double h = 0.0, m = 0.0, q = 0.0;
            for (int b = 0; b < D; ++b) {
                h += d[b] * H[b * D + a];
                m += d[b] * Ma[b * D + a];
                q += d[b] * P[b * D + a];
            }
            left[i * C + a] = h;
            row += m * d[a];
            one += q * d[a];
        }
        left[i * C + D] = row;
        p1[i] = one;
    }
    for (int64_t j = 0; j < Np; ++j) {
        const int64_t p = cols[j];
        for (int a = 0; a < D; ++a) d[a] = X[p * D + a] - mu[a];
        double col = lp ? lp[p] : 0.0;
        for (int a = 0; a < D; ++a) {
            double m = 0.0;
            for (int b = 0; b < D; ++b) m += d[b] * Mb[b * D + a];
            col += m * d[a];
            right[a * Np + j] = d[a];
        }
        right[D * Np + j] = col;
    }
    hgpdm_exp_f64(N, p1);
}

/* Entries of one stream's contraction work space (one_stream): acc [Np], prow [D, Np],
   Su [P, Up], left [N, D + 1], right [D + 1, Np] and phiR [4, Up]. */
#define PSI2_WORK(D, N, Np, Up) \
    (((D) + 1) * (Np) + (D) * ((D) + 1) / 2 * (Up) + ((D) + 1) * ((N) + (Np)) + 4 * (Up))

/* One stream's psi2 contraction: its exponent factors and psi1 [N] (p1), the group sums
   T [U, Up] and out [P + 1, Kp] (module comment); work as hgpdm_psi2_groups_f64's. */
INLINE void one_stream(const int D, int64_t U, int64_t L, int64_t Up, int64_t Kp, int64_t K,
                       const double *X, const int64_t *cols, const double *mu, const double *Q,
                       const double *c, const double *lp, const double *beta,
                       const double *betac, const double *kinv, const double *phiT, double *T,
                       double *out, double *p1, double *work) {
    const int64_t N = U * L, Np = L * Up, P = D * (D + 1) / 2, C = D + 1;
    double *acc = work, *prow = work + Np, *Su = prow + D * Np, *left = Su + P * Up;
    double *right = left + N * C, *phiR = right + C * Np;
    /* K values of which the last K % 8 <= 4 as dot products (contract): a vector of values
       would carry 4 to 7 zero ones */
    const int64_t Kd = K % W && K % W <= 4 ? K % W : 0, Kv = Kd ? K - Kd : Kp;
    for (int64_t r = 0; r < Kd; ++r)
        for (int64_t v = 0; v < Up; ++v) phiR[r * Up + v] = phiT[v * Kp + Kv + r];
    exponent(D, N, Np, X, cols, mu, Q, c, lp, left, right, p1);
    for (int64_t j = 0; j < (P + 1) * Kp; ++j) out[j] = 0.0;
    for (int64_t u = 0; u < U; ++u, T += Up) {
        group_rows(D, L, C, Np, left + u * L * C, right, beta + u * L * D, kinv + u * L * Np, prow,
                   acc);
        group_sums(D, L, Up, acc, prow, betac, T, Su);
        contract(P, Up, Kp, Kv, Kd, phiR, Su, phiT, phiT + u * Kp, out);
        contract(1, Up, Kp, Kv, Kd, phiR, T, phiT, phiT + u * Kp, out + P * Kp); /* the trace */
    }
}

INLINE void all_streams(const int D, int64_t S, int64_t U, int64_t L, int64_t Up, int64_t Kp,
                        const double *X, const int64_t *cols, const double *mu, const double *Q,
                        const double *c, const double *lp, const double *beta,
                        const double *betac, const double *kinv, const double *phiT, double *T,
                        double *out, double *p1, double *work) {
    const int64_t N = U * L, P = D * (D + 1) / 2;
    for (int64_t s = 0; s < S; ++s)
        one_stream(D, U, L, Up, Kp, Kp, X, cols, mu + s * D, Q + s * 4 * D * D, c + 2 * s,
                   lp ? lp + s * N : 0, beta, betac, kinv, phiT, T + s * U * Up,
                   out + s * (P + 1) * Kp, p1 + s * N, work);
}

/* Shapes (all C-contiguous; float64 but cols): X [N, D] the points in group order (u, l),
   cols [Np] (int64, in 0 .. N - 1) the point of each column, mu [S, D], Q [S, 4, D, D] (H, Ma,
   Mb, P), c [S, 2] (c, c1), lp [S, N] or NULL, beta [N, D], betac [D, Np], kinv [N, Np],
   phiT [Up, Kp] (phi[k, v]; zero at padding v and k >= K, Kp a multiple of 8), T [S, U, Up],
   out [S, D (D + 1) / 2 + 1, Kp], p1 [S, N] (psi1 = exp(d^T P d + c1 + lp)),
   work [PSI2_WORK(D, N, Np, Up)]. Returns 0, or 1 for D outside
   1..MAX_D (nothing written). */
int hgpdm_psi2_groups_f64(int64_t S, int64_t U, int64_t L, int64_t Up, int64_t D, int64_t Kp,
                          const double *X, const int64_t *cols, const double *mu,
                          const double *Q, const double *c, const double *lp,
                          const double *beta, const double *betac, const double *kinv,
                          const double *phiT, double *T, double *out, double *p1,
                          double *work) {
    const unsigned int csr = ftz_begin();
    int status;
#define PSI2(DD) \
    all_streams(DD, S, U, L, Up, Kp, X, cols, mu, Q, c, lp, beta, betac, kinv, phiT, T, out, p1, work)
    FOR_D(D, PSI2, status);
#undef PSI2
    _mm_setcsr(csr); /* the caller's */
    return status;
}

/* ---- The online filter's predictive step, fused with the contraction ----

   hgpdm_torch.inference.intention.compiled: for each stream, the transition moments of the K
   grid values (SharedTransition.moments), the GP-ADF update of each by the linear measurement
   (LinearMeasurement.update), the belief step (belief_step) and the moment-matched mixture
   (mixture_moments), in the order and form of those functions, with nothing of one stream but
   its state and status left in memory. */

#define LOG_2PI 1.8378770664093454835606594728112353

/* The lower Cholesky factor F of the n x n symmetric A (lower triangle read), row-major; 1
   where a pivot is not positive or is NaN (the caller's torch path then decides), else 0. */
static int cholesky(int64_t n, const double *A, double *F) {
    for (int64_t i = 0; i < n; ++i)
        for (int64_t j = 0; j <= i; ++j) {
            double s = A[i * n + j];
            for (int64_t q = 0; q < j; ++q) s -= F[i * n + q] * F[j * n + q];
            if (i == j) {
                if (!(s > 0.0)) return 1;
                F[i * n + i] = sqrt(s);
            } else {
                F[i * n + j] = s / F[j * n + j];
            }
        }
    return 0;
}

/* x [n, m] = F^-1 b for the lower-triangular F [n, n]; b [n, m], row-major. */
static void forward(int64_t n, int64_t m, const double *F, const double *b, double *x) {
    for (int64_t i = 0; i < n; ++i)
        for (int64_t j = 0; j < m; ++j) {
            double s = b[i * m + j];
            for (int64_t q = 0; q < i; ++q) s -= F[i * n + q] * x[q * m + j];
            x[i * m + j] = s / F[i * n + i];
        }
}

/* Fi [n, n] = F^-1 for the lower-triangular F [n, n] (zeros above the diagonal). */
static void tri_inverse(int64_t n, const double *F, double *Fi) {
    for (int64_t j = 0; j < n; ++j)
        for (int64_t i = 0; i < n; ++i) {
            if (i < j) {
                Fi[i * n + j] = 0.0;
                continue;
            }
            double t = i == j ? 1.0 : 0.0;
            for (int64_t q = j; q < i; ++q) t -= F[i * n + q] * Fi[q * n + j];
            Fi[i * n + j] = t / F[i * n + i];
        }
}

/* The exponents' quadratic forms of one RBF term for an input covariance Sigma [D, D], as
   hgpdm_torch.expectations.rbf_psi2_quadratic (the term with itself) and rbf_psi1_quadratic
   compute them, in their order and form: Q [4, D, D] = H, M_a, M_b (= M_a), P and c [2] = the
   psi2 constant and psi1's with log(coef). B = I + S Sigma S (S = diag(sqrt(w)), the weights
   2 w for psi2) is at least I, so its factor exists for any covariance; 1 where Sigma has a NaN
   or inf entry or B does not factorise (the caller's torch path then raises, or adds its
   jitter, as it would without this function). */
static int rbf_forms(const int D, const double *Sigma, const double *w, double coef, double *Q,
                     double *c) {
    double s[MAX_D], A[MAX_D * MAX_D], F[MAX_D * MAX_D], Fi[MAX_D * MAX_D], Bi[MAX_D * MAX_D];
    double *H = Q, *Ma = Q + D * D, *Mb = Q + 2 * D * D, *P = Q + 3 * D * D;
    for (int a = 0; a < D * D; ++a) /* torch's factor refuses any NaN or inf, both triangles */
        if (!isfinite(Sigma[a])) return 1;
    for (int pass = 0; pass < 2; ++pass) { /* psi2 (weights w + w), then psi1 (w) */
        for (int a = 0; a < D; ++a) {
            const double wa = pass == 0 ? w[a] + w[a] : w[a];
            s[a] = wa > 0.0 ? sqrt(wa) : 0.0;
        }
        for (int a = 0; a < D; ++a)
            for (int b = 0; b < D; ++b)
                A[a * D + b] = (a == b ? 1.0 : 0.0) + s[a] * Sigma[a * D + b] * s[b];
        if (cholesky(D, A, F)) return 1;
        double logdet = 0.0;
        for (int a = 0; a < D; ++a) logdet += log(fabs(F[a * D + a]));
        logdet *= 2.0;
        tri_inverse(D, F, Fi); /* B^-1 = F^-T F^-1 */
        for (int a = 0; a < D; ++a)
            for (int b = 0; b < D; ++b) {
                double t = 0.0;
                for (int q = a > b ? a : b; q < D; ++q) t += Fi[q * D + a] * Fi[q * D + b];
                Bi[a * D + b] = t;
            }
        if (pass == 0) {
            for (int a = 0; a < D; ++a)
                for (int b = 0; b < D; ++b) {
                    const double da = w[a] * (s[a] > 0.0 ? 1.0 / s[a] : 0.0);
                    const double db = w[b] * (s[b] > 0.0 ? 1.0 / s[b] : 0.0);
                    const double C = (a == b ? 1.0 : 0.0) - Bi[a * D + b]; /* I - B^-1 */
                    H[a * D + b] = da * C * db;
                }
            for (int a = 0; a < D; ++a)
                for (int b = 0; b < D; ++b)
                    Ma[a * D + b] = Mb[a * D + b] = 0.5 * (H[a * D + b] - (a == b ? w[a] : 0.0));
            c[0] = log(coef * coef) - 0.5 * logdet;
        } else {
            for (int a = 0; a < D; ++a)
                for (int b = 0; b < D; ++b) P[a * D + b] = -0.5 * s[a] * Bi[a * D + b] * s[b];
            c[1] = -0.5 * logdet + log(coef);
        }
    }
    return 0;
}

/* rbf_forms for S covariances Sigma [S, D, D]: Q [S, 4, D, D], c [S, 2], status [S] (int64).
   Returns 0, or 1 for D outside 1..MAX_D (nothing written). */
int hgpdm_rbf_forms_f64(int64_t S, int64_t D, const double *Sigma, const double *w, double coef,
                        double *Q, double *c, int64_t *status) {
    if (D < 1 || D > MAX_D) return 1;
    for (int64_t k = 0; k < S; ++k)
        status[k] = rbf_forms((int)D, Sigma + k * D * D, w, coef, Q + k * 4 * D * D, c + 2 * k);
    return 0;
}

/* The transition's K predictive moments from one stream's contraction (p1 [N], out [P + 1,
   Kp]), as SharedTransition.moments forms them. trans: phi [K, U], the process noise [K],
   scale2 [D], offset [D], the kernel's coefficient. Writes means [K, D] and covs [K, D, D];
   mu_u [U D] is work. */
static void transition_moments(const int D, int64_t U, int64_t L, int64_t K, int64_t Kp,
                               const double *p1, const double *beta, const double *out,
                               const double *trans, double *means, double *covs, double *mu_u) {
    const int64_t P = D * (D + 1) / 2;
    const double *phi = trans, *noise = phi + K * U, *scale2 = noise + K, *offset = scale2 + D;
    const double coef = offset[D];
    /* psi1 against each group's weights, then phi */
    for (int64_t u = 0; u < U; ++u)
        for (int d = 0; d < D; ++d) {
            double s = 0.0;
            for (int64_t l = 0; l < L; ++l) s += p1[u * L + l] * beta[(u * L + l) * D + d];
            mu_u[u * D + d] = s;
        }
    for (int64_t k = 0; k < K; ++k) {
        double *mk = means + k * D, *Pk = covs + k * D * D;
        for (int d = 0; d < D; ++d) {
            double s = 0.0;
            for (int64_t u = 0; u < U; ++u) s += phi[k * U + u] * mu_u[u * D + d];
            mk[d] = s;
        }
        double var = coef - out[P * Kp + k];
        var = (var < 0.0 ? 0.0 : var) + noise[k]; /* clamp_min keeps NaN */
        for (int64_t e = 0, i = 0; i < D; ++i)
            for (int64_t j = i; j < D; ++j, ++e)
                Pk[i * D + j] = Pk[j * D + i] = out[e * Kp + k] - mk[i] * mk[j];
        for (int d = 0; d < D; ++d) {
            Pk[d * D + d] += var * scale2[d];
            mk[d] += offset[d];
        }
    }
}

/* out [n, n] = sym(M P M^T) for M [n, D] and a symmetric P [D, D], as (M P) M^T with the two
   triangles averaged; MP [n, D] is work. */
static void congruence(const int D, int64_t n, const double *M, const double *P, double *MP,
                       double *out) {
    for (int64_t i = 0; i < n; ++i)
        for (int j = 0; j < D; ++j) {
            double t = 0.0;
            for (int d = 0; d < D; ++d) t += M[i * D + d] * P[d * D + j];
            MP[i * D + j] = t;
        }
    for (int64_t i = 0; i < n; ++i)
        for (int64_t o = 0; o < n; ++o) {
            double t = 0.0;
            for (int d = 0; d < D; ++d) t += MP[i * D + d] * M[o * D + d];
            out[i * n + o] = t;
        }
    for (int64_t i = 0; i < n; ++i)
        for (int64_t o = 0; o < i; ++o)
            out[i * n + o] = out[o * n + i] = 0.5 * (out[i * n + o] + out[o * n + i]);
}

/* The linear measurement (LinearMeasurement.update; meas: U [Dz, R], R [R, D], Q [D, D],
   offset [Dz], scale [Dz], noise, log_scale2) at N(mk, Pk), the parts that do not depend on
   z: with v = tr(Q (Pk + mk mk^T)) + noise and F = chol(R Pk R^T + v I), A = F^-1 R Pk
   [R, D], G = F^-1 [R, R], c = G R mk [R], iv = 1 / v and the innovation covariance's
   log-determinant; RP [R, D], S and F [R, R] are work. 1 where the covariance does not
   factorise. */
static int meas_factors(const int D, int64_t Dz, int64_t R, const double *meas, const double *mk,
                        const double *Pk, double *A, double *G, double *c, double *iv,
                        double *logdet, double *RP, double *S, double *F) {
    const double *Rm = meas + Dz * R, *Qm = Rm + R * D, *zscale = Qm + D * D + Dz;
    const double mnoise = zscale[Dz], log_scale2 = zscale[Dz + 1];
    double v = 0.0;
    for (int i = 0; i < D; ++i)
        for (int j = 0; j < D; ++j) v += Qm[i * D + j] * (Pk[i * D + j] + mk[i] * mk[j]);
    v += mnoise;
    congruence(D, R, Rm, Pk, RP, S);
    for (int64_t q = 0; q < R; ++q) S[q * R + q] += v;
    if (cholesky(R, S, F)) return 1;
    forward(R, D, F, RP, A);
    tri_inverse(R, F, G);
    double ld = 0.0;
    for (int64_t q = 0; q < R; ++q) {
        ld += log(fabs(F[q * R + q]));
        double t = 0.0; /* (R mk)_q, then G against it */
        for (int d = 0; d < D; ++d) t += mk[d] * Rm[q * D + d];
        S[q] = t;
    }
    for (int64_t q = 0; q < R; ++q) {
        double t = 0.0;
        for (int64_t o = 0; o <= q; ++o) t += G[q * R + o] * S[o];
        c[q] = t;
    }
    *logdet = 2.0 * ld + (double)(Dz - R) * log(v) + log_scale2;
    *iv = 1.0 / v;
    return 0;
}

/* Whether z [Dz] is missing (all NaN). */
static int all_nan(int64_t Dz, const double *z) {
    int missing = 1;
    for (int64_t i = 0; i < Dz; ++i) missing &= isnan(z[i]) != 0;
    return missing;
}

/* Lanes: the observations of a block of nl particles (or one stream's, nl = 1), each quantity
   stored lane-last ([..., nl]) and held in one vector register (lv_load / lv_store: lanes at
   and above nl read 0 and are not written); missing is a mask, bit p set where lane p's
   observation is missing. */
#define LANES W
#define SET1 _mm512_set1_pd

INLINE __m512d lv_load(const int nl, const double *x) {
    return nl == W ? _mm512_loadu_pd(x) : _mm512_maskz_loadu_pd(LANE_MASK(nl), x);
}

INLINE void lv_store(const int nl, double *x, __m512d v) {
    if (nl == W)
        _mm512_storeu_pd(x, v);
    else
        _mm512_mask_storeu_pd(x, LANE_MASK(nl), v);
}

/* z [Dz, nl] in the measurement's scaled units z~ = (z - offset) / scale (0 in a missing
   lane), projected on its latent span: zu = U^T z~ [R, nl], and the squared norm of the rest
   perp = |z~ - U U^T z~|^2 [nl] (the same for every value); zs [Dz, nl] is work. */
INLINE void project(const int D, int64_t Dz, int64_t R, const int nl,
                    const double *restrict meas, const double *restrict z, __mmask8 missing,
                    double *restrict zs, double *restrict zu, double *restrict perp) {
    const double *Um = meas, *zoff = meas + Dz * R + R * D + D * D, *zscale = zoff + Dz;
    for (int64_t i = 0; i < Dz; ++i)
        lv_store(nl, zs + i * nl,
                 _mm512_maskz_div_pd((__mmask8)~missing,
                                     _mm512_sub_pd(lv_load(nl, z + i * nl), SET1(zoff[i])),
                                     SET1(zscale[i])));
    for (int64_t q = 0; q < R; ++q) {
        __m512d t = _mm512_setzero_pd();
        for (int64_t i = 0; i < Dz; ++i)
            t = _mm512_fmadd_pd(lv_load(nl, zs + i * nl), SET1(Um[i * R + q]), t);
        lv_store(nl, zu + q * nl, t);
    }
    __m512d t = _mm512_setzero_pd();
    for (int64_t i = 0; i < Dz; ++i) {
        __m512d u = _mm512_setzero_pd();
        for (int64_t q = 0; q < R; ++q)
            u = _mm512_fmadd_pd(lv_load(nl, zu + q * nl), SET1(Um[i * R + q]), u);
        const __m512d r = _mm512_sub_pd(lv_load(nl, zs + i * nl), u);
        t = _mm512_fmadd_pd(r, r, t);
    }
    lv_store(nl, perp, t);
}

/* The evidence ll [nl] = log N(z | mk, Pk) of observed z (zu [R, nl], perp [nl] from project;
   A, G, c, iv, logdet from meas_factors) and the posterior means m_out [D, nl] = mk + A^T a,
   a = F^-1 (zu - R mk) = G zu - c [R, nl]. */
INLINE void condition(const int D, int64_t Dz, int64_t R, const int nl,
                      const double *restrict A, const double *restrict G,
                      const double *restrict c, double iv, double logdet,
                      const double *restrict mk, const double *restrict zu,
                      const double *restrict perp, double *restrict m_out,
                      double *restrict ll) {
    __m512d a[MAX_D], l = _mm512_mul_pd(lv_load(nl, perp), SET1(iv));
    for (int64_t q = 0; q < R; ++q) { /* R <= D <= MAX_D */
        __m512d aq = SET1(-c[q]);
        for (int64_t o = 0; o <= q; ++o)
            aq = _mm512_fmadd_pd(SET1(G[q * R + o]), lv_load(nl, zu + o * nl), aq);
        a[q] = aq;
        l = _mm512_fmadd_pd(aq, aq, l);
    }
    for (int i = 0; i < D; ++i) {
        __m512d t = _mm512_setzero_pd();
        for (int64_t q = 0; q < R; ++q) t = _mm512_fmadd_pd(SET1(A[q * D + i]), a[q], t);
        lv_store(nl, m_out + i * nl, _mm512_add_pd(SET1(mk[i]), t));
    }
    l = _mm512_add_pd(_mm512_add_pd(l, SET1(logdet)), SET1((double)Dz * LOG_2PI));
    lv_store(nl, ll, _mm512_mul_pd(SET1(-0.5), l));
}

/* The posterior covariance Pk - A^T A in place (lower triangle formed, mirrored). */
static void downdate(const int D, int64_t R, const double *A, double *Pk) {
    for (int i = 0; i < D; ++i)
        for (int j = 0; j <= i; ++j) {
            double s = 0.0;
            for (int64_t q = 0; q < R; ++q) s += A[q * D + i] * A[q * D + j];
            Pk[i * D + j] = Pk[j * D + i] = Pk[i * D + j] - s;
        }
}

/* The belief step B_t = keep B_{t-1} + E_t / T (lb, evidence ll [K, nl]; none in a missing
   lane), normalised into lb_out [K, nl], and the moment-matched mixture of the K Gaussians
   under it, m = sum_k p_k m_k and P = sum_k p_k (P_k + (m_k - m)(m_k - m)^T): means [K, D, nl]
   (overwritten by m_k - m), the k-th covariance at post + k cstride, or at prior + k cstride
   in a missing lane; m [D, nl], Pm [D, D, nl]; prob [K, nl] is work. */
INLINE void belief_mixture(const int D, int64_t K, const int nl, double keep, double temp,
                           const double *restrict lb, const double *restrict ll,
                           __mmask8 missing, double *restrict means, const double *post,
                           const double *prior, int64_t cstride, double *restrict m,
                           double *restrict Pm, double *restrict lb_out,
                           double *restrict prob) {
    const __mmask8 seen = (__mmask8)~missing;
    __m512d top = SET1(-INFINITY), total = _mm512_setzero_pd();
    for (int64_t k = 0; k < K; ++k) {
        const __m512d e = _mm512_maskz_div_pd(seen, lv_load(nl, ll + k * nl), SET1(temp));
        const __m512d b = _mm512_fmadd_pd(SET1(keep), lv_load(nl, lb + k * nl), e);
        lv_store(nl, lb_out + k * nl, b);
        const __mmask8 up = _mm512_cmp_pd_mask(b, top, _CMP_GT_OQ) |
                            _mm512_cmp_pd_mask(b, b, _CMP_UNORD_Q); /* NaN propagates */
        top = _mm512_mask_blend_pd(up, top, b);
    }
    for (int64_t k = 0; k < K; ++k) { /* p_k = exp(B_k - top) / sum_j exp(B_j - top) */
        const __m512d e = exp8(_mm512_sub_pd(lv_load(nl, lb_out + k * nl), top));
        lv_store(nl, prob + k * nl, e);
        total = _mm512_add_pd(total, e);
    }
    double tp[W], tt[W]; /* the log normaliser, in top */
    _mm512_storeu_pd(tp, top);
    _mm512_storeu_pd(tt, total);
    for (int p = 0; p < nl; ++p) tp[p] = isinf(tp[p]) && tp[p] < 0 ? tp[p] : tp[p] + log(tt[p]);
    top = _mm512_loadu_pd(tp);
    for (int64_t k = 0; k < K; ++k) {
        lv_store(nl, lb_out + k * nl, _mm512_sub_pd(lv_load(nl, lb_out + k * nl), top));
        lv_store(nl, prob + k * nl, _mm512_div_pd(lv_load(nl, prob + k * nl), total));
    }
    __m512d mv[MAX_D];
    for (int d = 0; d < D; ++d) {
        __m512d t = _mm512_setzero_pd();
        for (int64_t k = 0; k < K; ++k)
            t = _mm512_fmadd_pd(lv_load(nl, prob + k * nl),
                                lv_load(nl, means + (k * D + d) * nl), t);
        mv[d] = t;
        lv_store(nl, m + d * nl, t);
    }
    for (int64_t k = 0; k < K; ++k)
        for (int d = 0; d < D; ++d) {
            double *x = means + (k * D + d) * nl;
            lv_store(nl, x, _mm512_sub_pd(lv_load(nl, x), mv[d]));
        }
    for (int i = 0; i < D; ++i)
        for (int j = 0; j <= i; ++j) {
            __m512d t = _mm512_setzero_pd(), c = t, cq = t;
            for (int64_t k = 0; k < K; ++k) {
                const __m512d w = lv_load(nl, prob + k * nl);
                const double *dk = means + k * D * nl;
                t = _mm512_fmadd_pd(_mm512_mul_pd(w, lv_load(nl, dk + i * nl)),
                                    lv_load(nl, dk + j * nl), t);
                c = _mm512_fmadd_pd(w, SET1(post[k * cstride + i * D + j]), c);
                /* the predictions' covariances only where a lane needs them */
                if (missing) cq = _mm512_fmadd_pd(w, SET1(prior[k * cstride + i * D + j]), cq);
            }
            const __m512d v = _mm512_add_pd(t, _mm512_mask_blend_pd(missing, c, cq));
            lv_store(nl, Pm + (i * D + j) * nl, v);
            lv_store(nl, Pm + (j * D + i) * nl, v);
        }
}

/* The step of one stream from its contraction (p1 [N], out [P + 1, Kp]): the transition
   moments, the GP-ADF update of each by the linear measurement, the belief step and the
   mixture (trans and meas as in transition_moments and meas_factors). Writes m [D], P [D, D],
   lb_out [K]; returns 1 where an innovation covariance does not factorise. */
static int step_tail(const int D, int64_t U, int64_t L, int64_t K, int64_t Kp, int64_t Dz,
                     int64_t R, const double *p1, const double *beta, const double *out,
                     const double *trans, const double *meas, double keep, double temp,
                     const double *z, const double *lb, double *m, double *Pm, double *lb_out,
                     double *w) {
    double *mu_u = w, *means = mu_u + U * D, *covs = means + K * D, *ll = covs + K * D * D;
    double *zs = ll + K, *zu = zs + Dz, *c = zu + R, *RP = c + R, *A = RP + R * D;
    double *S = A + R * D, *F = S + R * R, *G = F + R * R, *prob = G + R * R, *mo = prob + K;
    transition_moments(D, U, L, K, Kp, p1, beta, out, trans, means, covs, mu_u);
    const __mmask8 missing = (__mmask8)all_nan(Dz, z);
    double perp;
    project(D, Dz, R, 1, meas, z, missing, zs, zu, &perp);
    for (int64_t k = 0; k < K; ++k) {
        double *mk = means + k * D, *Pk = covs + k * D * D, iv, logdet;
        if (meas_factors(D, Dz, R, meas, mk, Pk, A, G, c, &iv, &logdet, RP, S, F)) return 1;
        ll[k] = 0.0;
        if (!missing) {
            condition(D, Dz, R, 1, A, G, c, iv, logdet, mk, zu, &perp, mo, ll + k);
            for (int d = 0; d < D; ++d) mk[d] = mo[d];
            downdate(D, R, A, Pk);
        }
    }
    belief_mixture(D, K, 1, keep, temp, lb, ll, missing, means, covs, covs, D * D, m, Pm,
                   lb_out, prob);
    return 0;
}

INLINE void all_steps(const int D, int64_t S, int64_t U, int64_t L, int64_t Up, int64_t Kp,
                      int64_t K, int64_t Dz, int64_t R, const double *X, const int64_t *cols,
                      const double *mu, const double *Q, const double *c, const double *lp,
                      const double *beta, const double *betac, const double *kinv,
                      const double *phiT, const double *trans, const double *meas, double keep,
                      double temp, const double *z, const double *lb, double *m, double *Pm,
                      double *lb_out, int64_t *status, double *work) {
    const int64_t N = U * L, Np = L * Up, P = D * (D + 1) / 2;
    double *T = work + PSI2_WORK(D, N, Np, Up), *out = T + U * Up;
    double *p1 = out + (P + 1) * Kp, *tail = p1 + N;
    for (int64_t s = 0; s < S; ++s) {
        one_stream(D, U, L, Up, Kp, K, X, cols, mu + s * D, Q + s * 4 * D * D, c + 2 * s,
                   lp ? lp + s * N : 0, beta, betac, kinv, phiT, T, out, p1, work);
        status[s] = step_tail(D, U, L, K, Kp, Dz, R, p1, beta, out, trans, meas, keep, temp,
                              z + s * Dz, lb + s * K, m + s * D, Pm + s * D * D, lb_out + s * K,
                              tail);
    }
}

/* Shapes: the contraction's operands as in hgpdm_psi2_groups_f64 (mu the state means, Q and c
   the forms of their covariances); K values, Dz observed dims, R = min(D, Dz); trans
   [K U + K + 2 D + 1] and meas [Dz R + R D + D D + 2 Dz + 2] (step_tail); keep = 1 -
   forgetting, temp the temperature; z [S, Dz], lb [S, K]; outputs m [S, D], Pm [S, D, D],
   lb_out [S, K], status [S] (int64: 0, or 1 where the stream's update is left to torch); work
   [psi2's + U Up + (P + 1) Kp + N + U D + K (D D + D + 2) + D + Dz + 2 R + 2 R D + 3 R R].
   Returns 0, or 1 for D outside 1..MAX_D (nothing written). */
int hgpdm_predictive_step_f64(int64_t S, int64_t U, int64_t L, int64_t Up, int64_t D, int64_t Kp,
                              int64_t K, int64_t Dz, int64_t R, const double *X,
                              const int64_t *cols, const double *mu, const double *Q,
                              const double *c, const double *lp, const double *beta,
                              const double *betac, const double *kinv, const double *phiT,
                              const double *trans, const double *meas, double keep, double temp,
                              const double *z, const double *lb, double *m, double *Pm,
                              double *lb_out, int64_t *status, double *work) {
    const unsigned int csr = ftz_begin(); /* a belief's probability below 2.3e-308 counts as 0 */
    int code;
#define STEP(DD)                                                                                 \
    all_steps(DD, S, U, L, Up, Kp, K, Dz, R, X, cols, mu, Q, c, lp, beta, betac, kinv, phiT, trans, \
              meas, keep, temp, z, lb, m, Pm, lb_out, status, work)
    FOR_D(D, STEP, code);
#undef STEP
    _mm_setcsr(csr); /* the caller's */
    return code;
}

/* ---- Monte-Carlo planning's particles (hgpdm_torch.decision.mcp) ----

   Every particle of a decision starts from one belief: the K transition moments, the
   measurement's factors at each (meas_factors) and the K distributions of the next
   observation are computed once (hgpdm_mcp_shared_f64); a particle then costs its draw, its
   observation's check, the conditioning of the K predictions on it (condition), the belief
   step and the mixture (hgpdm_mcp_particles_f64): the online step's own algebra.

   Each value's block of the shared state, BLOCK(D, Dz, R) entries: the prediction m [D] and
   P [D, D], the posterior covariance P - A^T A [D, D], A [R, D], G [R, R], c [R], 1 / v, the
   log-determinant (meas_factors), and the observation's mean mz [Dz] and the lower Cholesky
   factor Lz of its covariance Sz, stored transposed (Lz^T [Dz, Dz]), as
   LinearMeasurement.moments forms them (W = (U R)^T diag(scale), mz = W^T m + offset,
   Sz = sym(W^T P W) + v diag(scale^2)). */
#define BLOCK(D, Dz, R) \
    ((D) + 2 * (D) * (D) + (R) * (D) + (R) * (R) + (R) + 2 + (Dz) + (Dz) * (Dz))
#define BLOCK_A(D) ((D) + 2 * (D) * (D))                          /* where A starts */
#define BLOCK_MZ(D, R) (BLOCK_A(D) + (R) * (D) + (R) * (R) + (R) + 2) /* where mz starts */

INLINE int mcp_shared(const int D, int64_t U, int64_t L, int64_t Up, int64_t Kp, int64_t K,
                      int64_t Dz, int64_t R, const double *X, const int64_t *cols,
                      const double *mu, const double *Q, const double *c, const double *lp,
                      const double *beta, const double *betac, const double *kinv,
                      const double *phiT, const double *trans, const double *meas,
                      double *shared, double *work) {
    const int64_t N = U * L, Np = L * Up, P = D * (D + 1) / 2, B = BLOCK(D, Dz, R);
    double *T = work + PSI2_WORK(D, N, Np, Up), *out = T + U * Up;
    double *p1 = out + (P + 1) * Kp, *mu_u = p1 + N, *means = mu_u + U * D;
    double *covs = means + K * D, *RP = covs + K * D * D, *S = RP + R * D, *F = S + R * R;
    double *Wm = F + R * R;
    double *cross = Wm + D * Dz, *Sz = cross + D * Dz;
    const double *Um = meas, *Rm = Um + Dz * R, *zoff = Rm + R * D + D * D, *zscale = zoff + Dz;
    one_stream(D, U, L, Up, Kp, K, X, cols, mu, Q, c, lp, beta, betac, kinv, phiT, T, out, p1,
               work);
    transition_moments(D, U, L, K, Kp, p1, beta, out, trans, means, covs, mu_u);
    for (int64_t i = 0; i < Dz; ++i) /* W^T = diag(scale) U R [Dz, D] */
        for (int d = 0; d < D; ++d) {
            double s = 0.0;
            for (int64_t q = 0; q < R; ++q) s += Um[i * R + q] * Rm[q * D + d];
            Wm[i * D + d] = s * zscale[i];
        }
    for (int64_t k = 0; k < K; ++k) {
        double *m = shared + k * B, *Pp = m + D, *Pq = Pp + D * D, *A = Pq + D * D;
        double *G = A + R * D, *c = G + R * R, *iv = c + R, *logdet = iv + 1, *mz = logdet + 1;
        double *Lz = mz + Dz;
        for (int d = 0; d < D; ++d) m[d] = means[k * D + d];
        for (int e = 0; e < D * D; ++e) Pp[e] = Pq[e] = covs[k * D * D + e];
        if (meas_factors(D, Dz, R, meas, m, Pp, A, G, c, iv, logdet, RP, S, F)) return 1;
        downdate(D, R, A, Pq);
        for (int64_t i = 0; i < Dz; ++i) {
            double s = 0.0;
            for (int d = 0; d < D; ++d) s += m[d] * Wm[i * D + d];
            mz[i] = s + zoff[i];
        }
        congruence(D, Dz, Wm, Pp, cross, Sz); /* W^T P W */
        for (int64_t i = 0; i < Dz; ++i) Sz[i * Dz + i] += zscale[i] * zscale[i] / *iv;
        for (int64_t e = 0; e < Dz * Dz; ++e) Lz[e] = 0.0;
        if (cholesky(Dz, Sz, Lz)) return 1;
        for (int64_t i = 0; i < Dz; ++i) /* stored transposed: a particle's draw reads rows */
            for (int64_t j = 0; j < i; ++j) {
                Lz[j * Dz + i] = Lz[i * Dz + j];
                Lz[i * Dz + j] = 0.0;
            }
    }
    return 0;
}

/* The shared state of the particles of one belief (mu [D] its mean, Q and c the forms of its
   covariance, lp [N] or NULL; the contraction's other operands as in hgpdm_psi2_groups_f64,
   trans and meas as in hgpdm_predictive_step_f64): shared [K, BLOCK(D, Dz, R)]; work [psi2's +
   U Up + (P + 1) Kp + N + U D + K (D D + D) + R D + 2 R R + 2 D Dz + Dz Dz]. Returns 0; 1 for D
   outside 1..MAX_D (nothing written); 2 where an innovation covariance does not factorise
   (the caller's torch path then takes the decision). */
int hgpdm_mcp_shared_f64(int64_t U, int64_t L, int64_t Up, int64_t D, int64_t Kp, int64_t K,
                         int64_t Dz, int64_t R, const double *X, const int64_t *cols,
                         const double *mu, const double *Q, const double *c, const double *lp,
                         const double *beta, const double *betac, const double *kinv,
                         const double *phiT, const double *trans, const double *meas,
                         double *shared, double *work) {
    const unsigned int csr = ftz_begin();
    int code, failed = 0;
#define SHARED(DD)                                                                               \
    failed = mcp_shared(DD, U, L, Up, Kp, K, Dz, R, X, cols, mu, Q, c, lp, beta, betac, kinv,    \
                        phiT, trans, meas, shared, work)
    FOR_D(D, SHARED, code);
#undef SHARED
    _mm_setcsr(csr); /* the caller's */
    return code ? code : 2 * failed;
}

/* The particles of one belief whose shared state is shared [K, BLOCK(D, Dz, R)] (lb [K] its
   normalised log-belief): particle i observes z = mz_g + Lz_g eps_i for g = g[i] (eps [I, Dz]),
   or z = eps_i where g is NULL; a z outside |z - center| <= limit or not finite (center,
   limit [Dz]: the filter's ObservationCheck) is treated as missing, as the filter treats it.
   They go in blocks of LANES (a short last block repeats its first particle); zo [I, Dz], where
   not NULL, receives the observations. The work space, PARTICLE_WORK(D, K, Dz, R) entries,
   holds a block's quantities lane-last. */
#define PARTICLE_WORK(D, K, Dz, R) \
    ((Dz) + LANES * (2 * (Dz) + (R) + 1 + 4 * (K) + (K) * (D) + (D) + (D) * (D)))
typedef struct {
    int64_t I, K, Dz, R;
    const double *shared, *meas, *center, *limit;
    double keep, temp;
    const int64_t *g;
    const double *eps;
    double *zo;
    double *zp, *z, *zs, *zu, *perp, *lbl, *ll, *lbo, *means, *m, *Pm, *prob; /* work */
} Particles;

INLINE void particles_init(const int D, Particles *pt, const double *lb, double *work) {
    const int64_t K = pt->K, Dz = pt->Dz, R = pt->R;
    pt->zp = work, pt->z = pt->zp + Dz, pt->zs = pt->z + Dz * LANES;
    pt->zu = pt->zs + Dz * LANES, pt->perp = pt->zu + R * LANES;
    pt->lbl = pt->perp + LANES, pt->ll = pt->lbl + K * LANES, pt->lbo = pt->ll + K * LANES;
    pt->means = pt->lbo + K * LANES, pt->m = pt->means + K * D * LANES;
    pt->Pm = pt->m + D * LANES, pt->prob = pt->Pm + D * D * LANES;
    for (int64_t k = 0; k < K; ++k) /* the shared belief in every lane */
        _mm512_storeu_pd(pt->lbl + k * LANES, SET1(lb[k]));
}

/* The block of particles i0 .. i0 + LANES - 1: their draws and checks, the conditioning of the
   K predictions, the belief step and the mixture, leaving m [D, LANES], Pm [D, D, LANES],
   lbo [K, LANES] and the normalised probabilities prob [K, LANES] in the work space. */
INLINE void particle_block(const int D, const Particles *pt, int64_t i0) {
    const int64_t I = pt->I, K = pt->K, Dz = pt->Dz, R = pt->R, B = BLOCK(D, Dz, R);
    const double *shared = pt->shared;
    double *zp = pt->zp, *z = pt->z;
    const __m512i lane_rows = _mm512_mullo_epi64(_mm512_set_epi64(7, 6, 5, 4, 3, 2, 1, 0),
                                                 _mm512_set1_epi64(LANES)); /* z [Dz, LANES] */
    __mmask8 missing = 0;
    for (int p = 0; p < LANES; ++p) { /* z = mz_g + Lz_g eps */
        const int64_t i = i0 + p < I ? i0 + p : i0;
        const double *e = pt->eps + i * Dz;
        if (pt->g) { /* Lz eps as a sum of Lz's columns (rows of Lz^T), eight rows of z at a time */
            const double *mz = shared + pt->g[i] * B + BLOCK_MZ(D, R);
            const double *LzT = mz + Dz;
            for (int64_t j0 = 0; j0 < Dz; j0 += W) {
                const __mmask8 k = TAIL_MASK(Dz, j0);
                const int64_t top = Dz - j0 < W ? Dz : j0 + W; /* LzT[q, j] = 0 for j < q */
                __m512d t = _mm512_setzero_pd();
                for (int64_t q = 0; q < top; ++q)
                    t = _mm512_fmadd_pd(SET1(e[q]), _mm512_maskz_loadu_pd(k, LzT + q * Dz + j0), t);
                t = _mm512_add_pd(_mm512_maskz_loadu_pd(k, mz + j0), t);
                _mm512_mask_storeu_pd(zp + j0, k, t);
            }
            e = zp;
        }
        int bad = 0; /* usable: finite, and |z - center| <= limit (NaN compares false) */
        for (int64_t j0 = 0; j0 < Dz; j0 += W) {
            const __mmask8 k = TAIL_MASK(Dz, j0);
            const __m512d x = _mm512_maskz_loadu_pd(k, e + j0);
            const __mmask8 finite = (__mmask8)~_mm512_fpclass_pd_mask(x, 0x99); /* NaN, inf */
            const __m512d c = _mm512_maskz_loadu_pd(k, pt->center + j0);
            const __m512d dev = _mm512_abs_pd(_mm512_sub_pd(x, c));
            const __mmask8 near = _mm512_mask_cmp_pd_mask(
                finite & k, dev, _mm512_maskz_loadu_pd(k, pt->limit + j0), _CMP_LE_OQ);
            bad |= near != k;
            _mm512_mask_i64scatter_pd(z + j0 * LANES + p, k, lane_rows, x, 8); /* lane p */
        }
        if (pt->zo && i0 + p < I)
            for (int64_t j = 0; j < Dz; ++j) pt->zo[i * Dz + j] = e[j];
        missing |= (__mmask8)(bad << p);
    }
    project(D, Dz, R, LANES, pt->meas, z, missing, pt->zs, pt->zu, pt->perp);
    for (int64_t k = 0; k < K; ++k) {
        const double *mk = shared + k * B, *A = mk + BLOCK_A(D), *G = A + R * D;
        const double *c = G + R * R;
        double *mo = pt->means + k * D * LANES, *lk = pt->ll + k * LANES;
        condition(D, Dz, R, LANES, A, G, c, c[R], c[R + 1], mk, pt->zu, pt->perp, mo, lk);
        if (missing) { /* a missing lane keeps the prediction */
            _mm512_storeu_pd(lk, _mm512_maskz_mov_pd((__mmask8)~missing, _mm512_loadu_pd(lk)));
            for (int d = 0; d < D; ++d)
                _mm512_storeu_pd(mo + d * LANES, _mm512_mask_blend_pd(
                                     missing, _mm512_loadu_pd(mo + d * LANES), SET1(mk[d])));
        }
    }
    /* the posterior covariances, or the predictions' in a missing lane */
    belief_mixture(D, K, LANES, pt->keep, pt->temp, pt->lbl, pt->ll, missing, pt->means,
                   shared + D + D * D, shared + D, B, pt->m, pt->Pm, pt->lbo, pt->prob);
}

INLINE void mcp_particles(const int D, Particles *pt, const double *lb, double *mean,
                          double *cov, double *lb_out, double *work) {
    const int64_t I = pt->I, K = pt->K;
    particles_init(D, pt, lb, work);
    for (int64_t i0 = 0; i0 < I; i0 += LANES) {
        particle_block(D, pt, i0);
        for (int p = 0; p < LANES && i0 + p < I; ++p) {
            const int64_t i = i0 + p;
            for (int d = 0; d < D; ++d) mean[i * D + d] = pt->m[d * LANES + p];
            for (int e = 0; e < D * D; ++e) cov[i * D * D + e] = pt->Pm[e * LANES + p];
            for (int64_t k = 0; k < K; ++k) lb_out[i * K + k] = pt->lbo[k * LANES + p];
        }
    }
}

/* Writes mean [I, D], cov [I, D, D], lb_out [I, K] and the observations zo [I, Dz] of the I
   particles (Particles); work [PARTICLE_WORK(D, K, Dz, R)]. Returns 0, or 1 for D outside
   1..MAX_D (nothing written). */
int hgpdm_mcp_particles_f64(int64_t I, int64_t D, int64_t K, int64_t Dz, int64_t R,
                            const double *shared, const double *meas, const double *center,
                            const double *limit, const double *lb, double keep, double temp,
                            const int64_t *g, const double *eps, double *mean, double *cov,
                            double *lb_out, double *zo, double *work) {
    const unsigned int csr = ftz_begin();
    Particles pt = {I, K, Dz, R, shared, meas, center, limit, keep, temp, g, eps, zo};
    int code;
#define PARTICLES(DD) mcp_particles(DD, &pt, lb, mean, cov, lb_out, work)
    FOR_D(D, PARTICLES, code);
#undef PARTICLES
    _mm_setcsr(csr); /* the caller's */
    return code;
}

/* ---- The planner's default values of beliefs (hgpdm_torch.decision: belief_vector, RadialBasis,
   LinearQ) ----

   For each belief (mean [D], cov [D, D], probabilities p [K]): the vector v = [mean, the upper
   triangle of cov row by row, p] (F = D + D (D + 1) / 2 + K), standardised z = (v - mu) / sd,
   the features phi_c = exp(min(0, -eta (|z|^2 + |c|^2) + 2 eta z.c)) of the C centres [C, F]
   (then a constant 1 where bias), and its values phi Wq^T (Wq [A, C + bias]), as those three
   compute them; beliefs in blocks of LANES. The work space, VALUES_WORK(C, F) entries, holds
   the centres' squared norms and a block's quantities lane-last. */
#define VALUES_WORK(C, F) ((C) + LANES * ((F) + (C) + 1))
typedef struct {
    int64_t F, C, A, bias;
    const double *mu, *sd, *centres, *Wq;
    double eta;
    double *cn, *z, *e, *zn; /* work; z [F, LANES] receives a block's vectors v */
} Values;

INLINE void values_init(Values *vl, double *work) {
    const int64_t C = vl->C, F = vl->F;
    vl->cn = work, vl->z = work + C, vl->e = vl->z + F * LANES, vl->zn = vl->e + C * LANES;
    for (int64_t c = 0; c < C; ++c) { /* |c|^2, eight entries at a time */
        const double *row = vl->centres + c * F;
        __m512d acc = _mm512_setzero_pd();
        for (int64_t f = 0; f < F; f += W) {
            const __m512d x = _mm512_maskz_loadu_pd(TAIL_MASK(F, f), row + f);
            acc = _mm512_fmadd_pd(x, x, acc);
        }
        vl->cn[c] = _mm512_reduce_add_pd(acc);
    }
}

/* The exponents of NC centres (from c0) for a block of lanes: e[c, lanes] = min(0, -eta (|z|^2
   + |c|^2) + 2 eta z.c), z [F, LANES] the standardised vectors (norm their |z|^2), with NC
   independent chains of FMAs over F held in registers; then their exponentials. */
INLINE void centre_exponents(const int NC, const Values *vl, int64_t c0, __m512d norm) {
    const int64_t F = vl->F;
    __m512d acc[8];
    for (int j = 0; j < NC; ++j) acc[j] = _mm512_setzero_pd();
    for (int64_t f = 0; f < F; ++f) {
        const __m512d zf = _mm512_loadu_pd(vl->z + f * LANES);
        for (int j = 0; j < NC; ++j)
            acc[j] = _mm512_fmadd_pd(SET1(vl->centres[(c0 + j) * F + f]), zf, acc[j]);
    }
    for (int j = 0; j < NC; ++j) {
        const __m512d x = _mm512_add_pd(
            _mm512_mul_pd(SET1(-vl->eta), _mm512_add_pd(norm, SET1(vl->cn[c0 + j]))),
            _mm512_mul_pd(SET1(2.0 * vl->eta), acc[j]));
        /* min(0, x) is x where x is NaN: clamp_max keeps NaN */
        _mm512_storeu_pd(vl->e + (c0 + j) * LANES, exp8(_mm512_min_pd(_mm512_setzero_pd(), x)));
    }
}

/* The values out [I, A] of the block of beliefs i0 .. whose vectors are in vl->z; with first
   >= 0, each belief's best value over the actions first .. A - 1 instead, out [I] (NaN where
   one of them is NaN, as torch's max). */
INLINE void block_values(const Values *vl, int64_t i0, int64_t I, int64_t first, double *out) {
    const int64_t F = vl->F, C = vl->C, A = vl->A, CB = C + vl->bias;
    __m512d norm = _mm512_setzero_pd();
    for (int64_t f = 0; f < F; ++f) {
        const __m512d zf = _mm512_div_pd(
            _mm512_sub_pd(_mm512_loadu_pd(vl->z + f * LANES), SET1(vl->mu[f])), SET1(vl->sd[f]));
        _mm512_storeu_pd(vl->z + f * LANES, zf);
        norm = _mm512_fmadd_pd(zf, zf, norm);
    }
    int64_t c0 = 0; /* the features' exponentials, eight centres at a time, then the rest */
    for (; c0 + 8 <= C; c0 += 8) centre_exponents(8, vl, c0, norm);
    if (c0 + 4 <= C) centre_exponents(4, vl, c0, norm), c0 += 4;
    if (c0 + 2 <= C) centre_exponents(2, vl, c0, norm), c0 += 2;
    if (c0 < C) centre_exponents(1, vl, c0, norm);
    __m512d best = SET1(-INFINITY);
    for (int64_t a = first < 0 ? 0 : first; a < A; ++a) { /* four partial sums over the centres */
        const double *wa = vl->Wq + a * CB, *e = vl->e;
        __m512d t[4] = {_mm512_setzero_pd(), _mm512_setzero_pd(), _mm512_setzero_pd(),
                        _mm512_setzero_pd()};
        int64_t c = 0;
        for (; c + 4 <= C; c += 4)
            for (int j = 0; j < 4; ++j)
                t[j] = _mm512_fmadd_pd(_mm512_loadu_pd(e + (c + j) * LANES), SET1(wa[c + j]), t[j]);
        for (; c < C; ++c)
            t[0] = _mm512_fmadd_pd(_mm512_loadu_pd(e + c * LANES), SET1(wa[c]), t[0]);
        __m512d v = _mm512_add_pd(_mm512_add_pd(t[0], t[1]), _mm512_add_pd(t[2], t[3]));
        if (vl->bias) v = _mm512_add_pd(v, SET1(wa[C]));
        if (first >= 0) { /* max(v, best) keeps best where v is NaN: the NaN is blended in */
            const __mmask8 nan = _mm512_cmp_pd_mask(v, v, _CMP_UNORD_Q);
            best = _mm512_mask_blend_pd(nan, _mm512_max_pd(v, best), v);
            continue;
        }
        _mm512_storeu_pd(vl->zn, v);
        for (int p = 0; p < LANES && i0 + p < I; ++p) out[(i0 + p) * A + a] = vl->zn[p];
    }
    if (first >= 0) {
        _mm512_storeu_pd(vl->zn, best);
        for (int p = 0; p < LANES && i0 + p < I; ++p) out[i0 + p] = vl->zn[p];
    }
}

/* The values out [I, A] of I beliefs (mean [I, D], cov [I, D, D], lb [I, K] log-probabilities,
   exponentiated here) with the basis mu, sd [F], centres [C, F], eta and the weights Wq
   [A, C + bias]; a short last block repeats its first belief. work [VALUES_WORK(C, F)]. */
int hgpdm_rbf_values_f64(int64_t I, int64_t D, int64_t K, int64_t C, int64_t A, int64_t bias,
                         const double *mean, const double *cov, const double *lb,
                         const double *mu, const double *sd, const double *centres, double eta,
                         const double *Wq, double *out, double *work) {
    const unsigned int csr = ftz_begin();
    Values vl = {D + D * (D + 1) / 2 + K, C, A, bias, mu, sd, centres, Wq, eta};
    values_init(&vl, work);
    const __m512i lane = _mm512_set_epi64(7, 6, 5, 4, 3, 2, 1, 0);
    for (int64_t i0 = 0; i0 < I; i0 += LANES) {
        /* the block's beliefs (a short last block repeats its first), gathered lane-last */
        const __mmask8 live = TAIL_MASK(I, i0);
        const __m512i row = _mm512_maskz_mov_epi64(live, lane);
        const __m512i im = _mm512_mullo_epi64(row, _mm512_set1_epi64(D));
        const __m512i ic = _mm512_mullo_epi64(row, _mm512_set1_epi64(D * D));
        const __m512i ik = _mm512_mullo_epi64(row, _mm512_set1_epi64(K));
        double *z = vl.z;
        int64_t f = 0;
        for (int64_t a = 0; a < D; ++a, ++f)
            _mm512_storeu_pd(z + f * LANES, _mm512_i64gather_pd(im, mean + i0 * D + a, 8));
        for (int64_t a = 0; a < D; ++a)
            for (int64_t b = a; b < D; ++b, ++f)
                _mm512_storeu_pd(z + f * LANES,
                                 _mm512_i64gather_pd(ic, cov + i0 * D * D + a * D + b, 8));
        for (int64_t k = 0; k < K; ++k, ++f)
            _mm512_storeu_pd(z + f * LANES, exp8(_mm512_i64gather_pd(ik, lb + i0 * K + k, 8)));
        block_values(&vl, i0, I, -1, out);
    }
    _mm_setcsr(csr); /* the caller's */
    return 0;
}

INLINE void mcp_values(const int D, Particles *pt, Values *vl, const double *lb, int64_t first,
                       double *out, double *work) {
    const int64_t I = pt->I, K = pt->K;
    particles_init(D, pt, lb, work);
    values_init(vl, work + PARTICLE_WORK(D, K, pt->Dz, pt->R));
    for (int64_t i0 = 0; i0 < I; i0 += LANES) {
        particle_block(D, pt, i0);
        double *z = vl->z; /* the block's belief vectors, lane-last already */
        int64_t f = 0;
        for (int a = 0; a < D; ++a, ++f)
            _mm512_storeu_pd(z + f * LANES, _mm512_loadu_pd(pt->m + a * LANES));
        for (int a = 0; a < D; ++a)
            for (int b = a; b < D; ++b, ++f)
                _mm512_storeu_pd(z + f * LANES, _mm512_loadu_pd(pt->Pm + (a * D + b) * LANES));
        for (int64_t k = 0; k < K; ++k, ++f)
            _mm512_storeu_pd(z + f * LANES, _mm512_loadu_pd(pt->prob + k * LANES));
        block_values(vl, i0, I, first, out);
    }
}

/* Each of the I particles' best value over the actions first .. A - 1, out [I] (block_values),
   of their beliefs (Particles; the arguments up to eps as in hgpdm_mcp_particles_f64) as
   hgpdm_rbf_values_f64 values them, from the particles' means, covariances and normalised
   probabilities (basis and weights as there), without the particles leaving the work space
   [PARTICLE_WORK(D, K, Dz, R) + VALUES_WORK(C, F)]. Returns 0, or 1 for D outside 1..MAX_D
   (nothing written). */
int hgpdm_mcp_values_f64(int64_t I, int64_t D, int64_t K, int64_t Dz, int64_t R,
                         const double *shared, const double *meas, const double *center,
                         const double *limit, const double *lb, double keep, double temp,
                         const int64_t *g, const double *eps, int64_t C, int64_t A, int64_t bias,
                         const double *mu, const double *sd, const double *centres, double eta,
                         const double *Wq, int64_t first, double *out, double *work) {
    const unsigned int csr = ftz_begin();
    Particles pt = {I, K, Dz, R, shared, meas, center, limit, keep, temp, g, eps, 0};
    Values vl = {D + D * (D + 1) / 2 + K, C, A, bias, mu, sd, centres, Wq, eta};
    int code;
#define VALUES(DD) mcp_values(DD, &pt, &vl, lb, first, out, work)
    FOR_D(D, VALUES, code);
#undef VALUES
    _mm_setcsr(csr); /* the caller's */
    return code;
}
