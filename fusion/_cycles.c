/* The filter cycles' matrices of fusion/errmodel.py, the covariance propagation and the updates of fusion/kf.py,
 * the distributed filter's fusion (fusion/dkf.py) and the still detector's interval sums (fusion/still.py), in C.
 *
 * Built with the package (setup.py) and called through ctypes by errmodel.segment_cycles and discrete_cycles,
 * KalmanFilter.propagate and kf.propagate_state, the engine's cycle slots, kf.joseph_update and kf.nis, the
 * consider analysis's cycles and updates, dkf.fuse and DistributedKF.propagate, smoother.rts and still.ImuSums.add;
 * it needs no Python headers.
 * The cycles (the updates, fusion and smoothing below say what they keep) evaluate errmodel.system_matrices (from
 * the Earth terms on, which errmodel.segment_cycles's kernel also forms from numpy's sines), errmodel.discretise
 * and the P cycle of KalmanFilter.propagate in the order their numpy source writes them, so the results equal
 * numpy's to the bit where numpy's matrix products are the sequential fused multiply-add sums of an optimised
 * BLAS: each product element c_ij is
 * fma(a_i,k-1, b_k-1,j, ... fma(a_i0, b_0j, +0.0)), in k order. OpenBLAS on x86-64 sums so for the sizes taken
 * here (15 x 15, 15 x 12, 15 x 9 and 3 x 3 results; not for every size: 18 x 18, for one, differs), which
 * tests/test_cycles_kernel.py checks. Elementwise steps are plain IEEE-754 operations, compiled without
 * contraction (-ffp-contract=off).
 *
 * Matrices are row-major doubles; a stack of m 15x15 matrices is (m, 15, 15). Frames and units are those of
 * fusion/errmodel.py: ENU navigation frame, body RFU, SI.
 */
#include <math.h>
#include <stdint.h>
#include <string.h>

#if defined(__GNUC__) && defined(__x86_64__) && !defined(__clang__)
/* fma() is a library call unless the target has the instruction: build a clone for it, chosen at load, with
 * every helper inlined into it (a helper compiled apart would call the library's fma() for each element) */
#define KERNEL __attribute__((target_clones("fma", "default")))
#define HELPER static inline __attribute__((always_inline))
#else
#define KERNEL
#define HELPER static inline
#endif

#define N 15  /* error states */
#define W 12  /* noise inputs */

enum { T_RM, T_RN, T_SL, T_CL, T_G, T_WIE, T_WEN = T_WIE + 3, T_N = T_WEN + 3 };

/* c (n x p) = a (n x k) @ b (k x p), with row strides lda, ldb, ldc; b read as its transpose when bt */
HELPER void matmul(int n, int k, int p, const double *a, int lda, const double *b, int ldb, int bt,
                          double *c, int ldc)
{
    for (int i = 0; i < n; i++) {
        double *ci = c + i * ldc;
        for (int j = 0; j < p; j++)
            ci[j] = 0.0;
        for (int l = 0; l < k; l++) {
            double ail = a[i * lda + l];
            if (bt)
                for (int j = 0; j < p; j++)
                    ci[j] = fma(ail, b[j * ldb + l], ci[j]);
            else
                for (int j = 0; j < p; j++)
                    ci[j] = fma(ail, b[l * ldb + j], ci[j]);
        }
    }
}

/* out = [v x] (3 x 3, row stride ld) with +0.0 off the skew entries, as earth.skew; negated when neg */
HELPER void skew(const double v[3], int neg, double *out, int ld)
{
    double s[9] = {0.0, -v[2], v[1], v[2], 0.0, -v[0], -v[1], v[0], 0.0};
    for (int r = 0; r < 3; r++)
        for (int c = 0; c < 3; c++)
            out[r * ld + c] = neg ? -s[r * 3 + c] : s[r * 3 + c];
}

/* F and G of errmodel.system_matrices for one cycle: omega the Earth rate (rad/s, earth.OMEGA_IE), terms (T_N)
 * from the numpy Earth functions, v (3) m/s,
 * C (3 x 3) C_bn, f (3) the cycle's mean specific force in ENU m/s^2 */
HELPER void system(double omega, const double *t, const double *v, const double *C, const double *f,
                   double F[N * N], double G[N * W])
{
    const double rm = t[T_RM], rn = t[T_RN], sl = t[T_SL], cl = t[T_CL], g = t[T_G];
    const double *w_ie = t + T_WIE, *w_en = t + T_WEN;
    const double tl = sl / cl, ve = v[0], vn = v[1];
    double d_ie_r[9] = {0.0}, d_en_r[9] = {0.0}, d_en_v[9] = {0.0}, sv[9], m[9], pr[9], tmp[3];
    d_ie_r[4] = -omega * sl / rm;
    d_ie_r[7] = omega * cl / rm;
    d_en_r[7] = ve / (cl * cl * rn * rm);
    d_en_r[2] = vn / (rm * rm);
    d_en_r[5] = -ve / (rn * rn);
    d_en_r[8] = -ve * tl / (rn * rn);
    d_en_v[3] = 1.0 / rn + 0.0;
    d_en_v[6] = tl / rn + 0.0;
    d_en_v[1] = -1.0 / rm + 0.0;
    skew(v, 0, sv, 3);
    memset(F, 0, sizeof(double) * N * N);
    memset(G, 0, sizeof(double) * N * W);
    skew(w_en, 1, F + 0 * N + 0, N);  /* F[POS, POS] = -[w_en x] */
    for (int i = 0; i < 3; i++)
        F[i * N + 3 + i] = 1.0;  /* F[POS, VEL] = I */
    for (int i = 0; i < 9; i++)
        m[i] = 2.0 * d_ie_r[i] + d_en_r[i];
    matmul(3, 3, 3, sv, 3, m, 3, 0, pr, 3);
    for (int r = 0; r < 3; r++)
        for (int c = 0; c < 3; c++)
            F[(3 + r) * N + c] = pr[r * 3 + c];  /* F[VEL, POS] */
    F[5 * N + 2] += 2.0 * g / sqrt(rm * rn);
    for (int i = 0; i < 3; i++)
        tmp[i] = 2.0 * w_ie[i] + w_en[i];
    skew(tmp, 1, m, 3);
    matmul(3, 3, 3, sv, 3, d_en_v, 3, 0, pr, 3);
    for (int r = 0; r < 3; r++)
        for (int c = 0; c < 3; c++)
            F[(3 + r) * N + 3 + c] = m[r * 3 + c] + pr[r * 3 + c];  /* F[VEL, VEL] */
    skew(f, 0, F + 3 * N + 6, N);  /* F[VEL, ATT] = [f x] */
    for (int i = 0; i < 3; i++)
        tmp[i] = w_ie[i] + w_en[i];
    skew(tmp, 1, F + 6 * N + 6, N);  /* F[ATT, ATT] = -[(w_ie + w_en) x] */
    for (int r = 0; r < 3; r++)
        for (int c = 0; c < 3; c++) {
            F[(3 + r) * N + 12 + c] = C[r * 3 + c];                  /* F[VEL, BA] = C */
            F[(6 + r) * N + c] = d_ie_r[r * 3 + c] + d_en_r[r * 3 + c];  /* F[ATT, POS] */
            F[(6 + r) * N + 3 + c] = d_en_v[r * 3 + c];              /* F[ATT, VEL] */
            F[(6 + r) * N + 9 + c] = -C[r * 3 + c];                  /* F[ATT, BG] = -C */
            G[(6 + r) * W + c] = -C[r * 3 + c];                      /* G[ATT, 0:3] = -C */
            G[(3 + r) * W + 3 + c] = C[r * 3 + c];                   /* G[VEL, 3:6] = C */
        }
    for (int i = 0; i < 3; i++) {
        G[(9 + i) * W + 6 + i] = 1.0;
        G[(12 + i) * W + 9 + i] = 1.0;
    }
}

/* Phi, Q (15, 15) of one cycle of d s (errmodel.system_matrices then errmodel.discretise): omega, t, v, C, f as
 * system's, q (12, 12) the noise PSD */
HELPER void cycle(double omega, const double *t, const double *v, const double *C, const double *f, double d,
                  const double *q, double *P, double *Qk)
{
    double F[N * N], G[N * W], Fdt[N * N], FF[N * N], Gq[N * W], GqG[N * N], FGqG[N * N], FGqGF[N * N];
    system(omega, t, v, C, f, F, G);
    for (int i = 0; i < N * N; i++)
        Fdt[i] = F[i] * d;
    matmul(N, N, N, Fdt, N, Fdt, N, 0, FF, N);
    for (int i = 0; i < N; i++)
        for (int j = 0; j < N; j++)
            P[i * N + j] = ((i == j ? 1.0 : 0.0) + Fdt[i * N + j]) + 0.5 * FF[i * N + j];
    matmul(N, W, W, G, W, q, W, 0, Gq, W);
    matmul(N, W, N, Gq, W, G, W, 1, GqG, N);
    matmul(N, N, N, F, N, GqG, N, 0, FGqG, N);
    matmul(N, N, N, FGqG, N, F, N, 1, FGqGF, N);
    const double d3 = d * d * d / 3.0;
    for (int i = 0; i < N; i++)
        for (int j = 0; j < N; j++)
            Qk[i * N + j] = (GqG[i * N + j] * d + 0.5 * (FGqG[i * N + j] + FGqG[j * N + i]) * d * d)
                            + FGqGF[i * N + j] * d3;
}

/* Phi, Q (m, 15, 15) of m cycles (errmodel.system_matrices then errmodel.discretise): omega as system's,
 * terms (m, T_N) as errmodel.discrete_cycles gives them, v (m, 3), C (m, 3, 3), f (m, 3), dt (m) s, q (12, 12) the
 * noise PSD */
KERNEL void fieldlog_cycle_matrices(int64_t m, double omega, const double *terms, const double *v,
                                    const double *C, const double *f, const double *dt, const double *q,
                                    double *Phi, double *Q)
{
    for (int64_t k = 0; k < m; k++)
        cycle(omega, terms + k * T_N, v + 3 * k, C + 9 * k, f + 3 * k, dt[k], q, Phi + k * N * N, Q + k * N * N);
}

enum { EARTH_A, EARTH_E2, EARTH_F, EARTH_M, EARTH_K, EARTH_GAMMA_E, EARTH_OMEGA_IE, EARTH_N };

/* The m cycles of an INS segment (errmodel.segment_cycles), each from sample ends[k - 1] (0 for the first) to
 * ends[k] (strictly increasing, below n), taken at its middle sample (start + end) / 2. In: the samples' times t
 * (n) s, bias-corrected rate w and specific force f (n, 3) rad/s and m/s^2 body RFU, the INS solution's q (n, 4)
 * (of C_bn), h (n) m, v (n, 3) ENU m/s; trig (3, m) numpy's sin, cos and tan of each middle sample's latitude;
 * e the Earth constants (EARTH_*, from fusion/earth.py); q_psd (12, 12). Out, per cycle: dt (m) s, the mean f and
 * w over (start, end] (m, 3 each; differences of the running sums from sample 1, numpy's cumsum), the middle
 * sample's C_bn (m, 3, 3; earth.quat_to_dcm), Phi and Q (m, 15, 15). The Earth terms are those of
 * errmodel.discrete_cycles (earth.principal_radii, gravity, omega_ie_n, omega_en_n), C_bn f_mean is summed in
 * np.einsum's order. Returns 1, writing nothing past the cycle found, when the ends are not as stated; else 0. */
KERNEL int fieldlog_segment_cycles(int64_t n, int64_t m, const int64_t *ends, const double *t, const double *w,
                                   const double *f, const double *q, const double *h, const double *v,
                                   const double *trig, const double *e, const double *q_psd, double *dt,
                                   double *f_mean, double *w_mean, double *C, double *Phi, double *Q)
{
    double sw[3] = {0.0, 0.0, 0.0}, sf[3] = {0.0, 0.0, 0.0}, sw0[3], sf0[3];
    int64_t i = 0, start = 0;
    memcpy(sw0, sw, sizeof sw);
    memcpy(sf0, sf, sizeof sf);
    for (int64_t k = 0; k < m; k++) {
        const int64_t end = ends[k], mid = (start + end) / 2;
        if (end <= start || end >= n)
            return 1;
        for (i = i + 1; i <= end; i++)
            for (int j = 0; j < 3; j++) {
                sw[j] = sw[j] + w[3 * i + j];
                sf[j] = sf[j] + f[3 * i + j];
            }
        i = end;
        dt[k] = t[end] - t[start];
        for (int j = 0; j < 3; j++) {
            w_mean[3 * k + j] = (sw[j] - sw0[j]) / (double)(end - start);
            f_mean[3 * k + j] = (sf[j] - sf0[j]) / (double)(end - start);
        }
        memcpy(sw0, sw, sizeof sw);
        memcpy(sf0, sf, sizeof sf);
        const double *qm = q + 4 * mid;
        const double nq = sqrt(((qm[0] * qm[0] + qm[1] * qm[1]) + qm[2] * qm[2]) + qm[3] * qm[3]);
        const double x = qm[0] / nq, y = qm[1] / nq, z = qm[2] / nq, s = qm[3] / nq;
        double *c = C + 9 * k, fn[3], terms[T_N];
        c[0] = 1.0 - 2.0 * (y * y + z * z);
        c[1] = 2.0 * (x * y - z * s);
        c[2] = 2.0 * (x * z + y * s);
        c[3] = 2.0 * (x * y + z * s);
        c[4] = 1.0 - 2.0 * (x * x + z * z);
        c[5] = 2.0 * (y * z - x * s);
        c[6] = 2.0 * (x * z - y * s);
        c[7] = 2.0 * (y * z + x * s);
        c[8] = 1.0 - 2.0 * (x * x + y * y);
        for (int r = 0; r < 3; r++)
            fn[r] = (c[3 * r] * f_mean[3 * k] + c[3 * r + 2] * f_mean[3 * k + 2]) + c[3 * r + 1] * f_mean[3 * k + 1];
        const double sl = trig[k], cl = trig[m + k], tl = trig[2 * m + k], hm = h[mid], s2 = sl * sl;
        const double a = e[EARTH_A], fl = e[EARTH_F], wq = sqrt(1.0 - e[EARTH_E2] * s2);
        const double r_n = a / wq, r_m = r_n * (1.0 - e[EARTH_E2]) / (wq * wq);
        const double g0 = e[EARTH_GAMMA_E] * (1.0 + e[EARTH_K] * s2) / sqrt(1.0 - e[EARTH_E2] * s2);
        const double *vm = v + 3 * mid;
        terms[T_RM] = r_m + hm;
        terms[T_RN] = r_n + hm;
        terms[T_SL] = sl;
        terms[T_CL] = cl;
        terms[T_G] = g0 * (1.0 - 2.0 / a * (1.0 + fl + e[EARTH_M] - 2.0 * fl * s2) * hm + 3.0 * hm * hm / (a * a));
        terms[T_WIE] = 0.0;
        terms[T_WIE + 1] = e[EARTH_OMEGA_IE] * cl;
        terms[T_WIE + 2] = e[EARTH_OMEGA_IE] * sl;
        terms[T_WEN] = -vm[1] / terms[T_RM];
        terms[T_WEN + 1] = vm[0] / terms[T_RN];
        terms[T_WEN + 2] = vm[0] * tl / terms[T_RN];
        cycle(e[EARTH_OMEGA_IE], terms, vm, c, fn, dt[k], q_psd, Phi + k * N * N, Q + k * N * N);
        start = end;
    }
    return 0;
}

/* The covariance cycles of KalmanFilter.propagate: P <- Phi_i P Phi_i^T + q_scale Q_i for i < m, made symmetric
 * (0.5 (P + P^T)) when sym; P (15, 15) in place, hist (m, 15, 15) gets P after each cycle */
HELPER void propagate_cov(int64_t m, const double *Phi, const double *Q, double q_scale, int sym, double *P,
                          double *hist)
{
    double A[N * N], B[N * N];
    for (int64_t k = 0; k < m; k++) {
        const double *F = Phi + k * N * N, *Qk = Q + k * N * N;
        matmul(N, N, N, F, N, P, N, 0, A, N);
        matmul(N, N, N, A, N, F, N, 1, B, N);
        for (int i = 0; i < N * N; i++)
            B[i] = B[i] + q_scale * Qk[i];
        for (int i = 0; i < N; i++)
            for (int j = 0; j < N; j++)
                P[i * N + j] = sym ? 0.5 * (B[i * N + j] + B[j * N + i]) : B[i * N + j];
        memcpy(hist + k * N * N, P, sizeof(double) * N * N);
    }
}

KERNEL void fieldlog_propagate_cov(int64_t m, const double *Phi, const double *Q, double q_scale, int32_t sym,
                                   double *P, double *hist)
{
    propagate_cov(m, Phi, Q, q_scale, sym, P, hist);
}

/* The error state through the cycles of KalmanFilter.propagate (kf.propagate_state): x <- Phi_i x for i < m, x (15)
 * in place; hist (m, 15) gets x after each cycle */
KERNEL void fieldlog_propagate_state(int64_t m, const double *Phi, double *x, double *hist)
{
    double y[N];
    for (int64_t k = 0; k < m; k++) {
        matmul(N, N, 1, Phi + k * N * N, N, x, 1, 0, y, 1);
        memcpy(x, y, sizeof y);
        memcpy(hist + k * N, y, sizeof y);
    }
}

/* The covariance cycles' slots (engine._slot_starts): out gets each k in [1, n) whose slot floor((t_k - anchor) /
 * step) (t in s, strictly increasing) differs from sample k - 1's, in order; returns their number */
int64_t fieldlog_slot_starts(int64_t n, const double *t, double anchor, double step, int64_t *out)
{
    int64_t count = 0, prev = 0;
    for (int64_t k = 0; k < n; k++) {
        int64_t slot = (int64_t)floor((t[k] - anchor) / step);
        if (k > 0 && slot != prev)
            out[count++] = k;
        prev = slot;
    }
    return count;
}

/* The consider sensitivity of fusion/consider.GyroConsider.propagate: S <- Phi_i S + 1/2 (Bdt_i + Phi_i Bdt_i) for
 * i < m, S (15, 9) in place; hist (m, 15, 9) gets S after each cycle. Bdt_i, the error-state change per unit of c
 * over cycle i, is formed from the cycle's C_bn (m, 3, 3), mean rate omega (m, 3, rad/s, body RFU) and length dt
 * (m, s): its attitude rows, column p, are -C_bn[:, axis_p] times rate_p, times dt (consider.py's order of c) */
KERNEL void fieldlog_consider_cycles(int64_t m, const double *Phi, const double *C_bn, const double *omega,
                                     const double *dt, double *S, double *hist)
{
    enum { K = 9, ATT0 = 6 };
    static const int axis[K] = {0, 1, 2, 0, 0, 1, 1, 2, 2}, rate[K] = {0, 1, 2, 1, 2, 0, 2, 0, 1};
    double A[N * K], B[N * K], Bk[N * K];
    for (int64_t k = 0; k < m; k++) {
        const double *F = Phi + k * N * N, *C = C_bn + k * 9, *w = omega + k * 3;
        for (int i = 0; i < N * K; i++)
            Bk[i] = 0.0 * dt[k];
        for (int r = 0; r < 3; r++)
            for (int p = 0; p < K; p++)
                Bk[(ATT0 + r) * K + p] = (-C[r * 3 + axis[p]] * w[rate[p]]) * dt[k];
        matmul(N, N, K, F, N, S, K, 0, A, K);
        matmul(N, N, K, F, N, Bk, K, 0, B, K);
        for (int i = 0; i < N * K; i++)
            S[i] = A[i] + 0.5 * (Bk[i] + B[i]);
        memcpy(hist + k * N * K, S, sizeof(double) * N * K);
    }
}

/* The interval sums of fusion/still.ImuSums.add: sum_w, sum_f (3 each) += the sums over the n rows of w and f
 * (n x 3), sum_ww, sum_ff += their sums of squares. Each column is summed from its first row on, one row after the
 * other, and the squares from +0.0: numpy's order for a sum over the rows of a C-contiguous array and for
 * einsum("ij,ij->j"), so the sums equal numpy's to the bit. */
void fieldlog_sample_sums(int64_t n, const double *w, const double *f, double *sum_w, double *sum_f,
                          double *sum_ww, double *sum_ff)
{
    const double *x[2] = {w, f};
    double *sums[2] = {sum_w, sum_f}, *squares[2] = {sum_ww, sum_ff};
    for (int a = 0; a < 2; a++)
        for (int j = 0; j < 3; j++) {
            double s = n > 0 ? x[a][j] : 0.0, sq = 0.0;
            for (int64_t i = 1; i < n; i++)
                s += x[a][i * 3 + j];
            for (int64_t i = 0; i < n; i++)
                sq += x[a][i * 3 + j] * x[a][i * 3 + j];
            sums[a][j] += s;
            squares[a][j] += sq;
        }
}

/* ---- the per-epoch updates: KalmanFilter.update (Joseph form) and DistributedKF's fusion (fusion/dkf.py) ----
 * Not bound to numpy's bits: LAPACK's solve and Cholesky order their sums their own way; these follow the same
 * formulas, and tests/test_cycles_kernel.py and the engine reference compare them with numpy to rounding. */

#define MAXM 32  /* measurement rows of one update (the callers fall back to numpy beyond) */

/* B (m x p, row stride p) <- S^-1 B, S (m x m) overwritten: Gaussian elimination with partial pivoting (as
 * LAPACK's gesv). Returns 1 when S is singular (a zero pivot), else 0. */
HELPER int lu_solve(int m, double *S, int p, double *B)
{
    for (int c = 0; c < m; c++) {
        int piv = c;
        for (int r = c + 1; r < m; r++)
            if (fabs(S[r * m + c]) > fabs(S[piv * m + c]))
                piv = r;
        if (S[piv * m + c] == 0.0)
            return 1;
        if (piv != c) {
            for (int j = 0; j < m; j++) {
                double t = S[c * m + j]; S[c * m + j] = S[piv * m + j]; S[piv * m + j] = t;
            }
            for (int j = 0; j < p; j++) {
                double t = B[c * p + j]; B[c * p + j] = B[piv * p + j]; B[piv * p + j] = t;
            }
        }
        for (int r = c + 1; r < m; r++) {
            double l = S[r * m + c] / S[c * m + c];
            for (int j = c + 1; j < m; j++)
                S[r * m + j] -= l * S[c * m + j];
            for (int j = 0; j < p; j++)
                B[r * p + j] -= l * B[c * p + j];
        }
    }
    for (int c = m - 1; c >= 0; c--) {
        for (int j = 0; j < p; j++) {
            double s = B[c * p + j];
            for (int k = c + 1; k < m; k++)
                s -= S[c * m + k] * B[k * p + j];
            B[c * p + j] = s / S[c * m + c];
        }
    }
    return 0;
}

/* out (15 x 15) = 0.5 (S + S^T) of S = a + b, kept in T (T may be a or b, out may be a) */
HELPER void sym_of_sum(const double *a, const double *b, double *T, double *out)
{
    for (int i = 0; i < N * N; i++)
        T[i] = a[i] + b[i];
    for (int i = 0; i < N; i++)
        for (int j = 0; j < N; j++)
            out[i * N + j] = 0.5 * (T[i * N + j] + T[j * N + i]);
}

/* K (15 x m) = P H^T (H P H^T + R)^-1 of covariance P (15 x 15), H (m x 15), R (m x m). Returns 1 when the
 * innovation covariance is singular. */
HELPER int kalman_gain(int m, const double *H, const double *R, const double *P, double *K)
{
    double HP[MAXM * N], S[MAXM * MAXM];
    matmul(m, N, N, H, N, P, N, 0, HP, N);
    matmul(m, N, m, HP, N, H, N, 1, S, m);
    for (int i = 0; i < m * m; i++)
        S[i] += R[i];
    if (lu_solve(m, S, N, HP))  /* HP <- S^-1 H P = K^T */
        return 1;
    for (int i = 0; i < N; i++)
        for (int j = 0; j < m; j++)
            K[i * m + j] = HP[j * N + i];
    return 0;
}

/* consider.GyroConsider.update: S (15 x 9) <- S - K (H S) in place, K = P H^T (H P H^T + R)^-1 the gain of an
 * update of covariance P (15 x 15) with H (m x 15), R (m x m). Returns 1 (S unchanged) when H P H^T + R is
 * singular. */
KERNEL int32_t fieldlog_consider_update(int64_t m, const double *H, const double *R, const double *P, double *S)
{
    enum { C = 9 };
    double K[N * MAXM], HS[MAXM * C], KHS[N * C];
    if (m < 0 || m > MAXM || kalman_gain((int)m, H, R, P, K))
        return 1;
    matmul((int)m, N, C, H, N, S, C, 0, HS, C);
    matmul(N, (int)m, C, K, (int)m, HS, C, 0, KHS, C);
    for (int i = 0; i < N * C; i++)
        S[i] -= KHS[i];
    return 0;
}

/* The normalised innovation squared of output.StatusBook.fix, (z - H x)^T S^-1 (z - H x) / m with S = H P H^T + R,
 * of an update with z (m), H (m x 15), R (m x m) on x (15) and P (15 x 15), into *nis. Returns 1 when S is
 * singular (or m is not in 1..MAXM). */
KERNEL int32_t fieldlog_nis(int64_t m, const double *z, const double *H, const double *R, const double *x,
                            const double *P, double *nis)
{
    double HP[MAXM * N], S[MAXM * MAXM], y[MAXM], b[MAXM];
    if (m < 1 || m > MAXM)
        return 1;
    const int mm = (int)m;
    matmul(mm, N, N, H, N, P, N, 0, HP, N);
    matmul(mm, N, mm, HP, N, H, N, 1, S, mm);
    for (int i = 0; i < mm * mm; i++)
        S[i] += R[i];
    for (int i = 0; i < mm; i++) {
        double s = 0.0;
        for (int k = 0; k < N; k++)
            s = fma(H[i * N + k], x[k], s);
        y[i] = b[i] = z[i] - s;
    }
    if (lu_solve(mm, S, 1, b))
        return 1;
    double q = 0.0;
    for (int i = 0; i < mm; i++)
        q = fma(y[i], b[i], q);
    *nis = q / mm;
    return 0;
}

/* KalmanFilter.update: x (15) and P (15 x 15) in place through the update with z (m), H (m x 15), R (m x m):
 * K = P H^T S^-1, dx = K (z - H x), x += dx, P <- sym(A P A^T + K R K^T) with A = I - K H (Joseph form). K
 * (15 x m) and dx (15) out; P12 (15 x 15, may be NULL) in place: A P12 (side 0) or P12 A^T (side 1), the
 * distributed filter's cross-covariance. Returns 1 (nothing changed) when S is singular. */
KERNEL int32_t fieldlog_kf_update(int64_t m, const double *z, const double *H, const double *R, double *x,
                                  double *P, double *K, double *dx, double *P12, int32_t side)
{
    double nu[MAXM], A[N * N], T[N * N], KR[N * MAXM], KRK[N * N];
    if (m < 0 || m > MAXM || kalman_gain((int)m, H, R, P, K))
        return 1;
    const int mm = (int)m;
    for (int i = 0; i < mm; i++) {
        double s = 0.0;
        for (int k = 0; k < N; k++)
            s = fma(H[i * N + k], x[k], s);
        nu[i] = z[i] - s;
    }
    for (int i = 0; i < N; i++) {
        double s = 0.0;
        for (int k = 0; k < mm; k++)
            s = fma(K[i * mm + k], nu[k], s);
        dx[i] = s;
        x[i] += s;
    }
    matmul(N, mm, N, K, mm, H, N, 0, A, N);
    for (int i = 0; i < N * N; i++)
        A[i] = ((i % (N + 1)) == 0 ? 1.0 : 0.0) - A[i];
    matmul(N, N, N, A, N, P, N, 0, T, N);
    matmul(N, N, N, T, N, A, N, 1, P, N);  /* A P A^T */
    matmul(N, mm, mm, K, mm, R, mm, 0, KR, mm);
    matmul(N, mm, N, KR, mm, K, mm, 1, KRK, N);
    sym_of_sum(P, KRK, T, P);
    if (P12) {
        memcpy(T, P12, sizeof T);
        if (side == 0)
            matmul(N, N, N, A, N, T, N, 0, P12, N);
        else
            matmul(N, N, N, T, N, A, N, 1, P12, N);
    }
    return 0;
}

/* out (15 x 15) = P^-1 of a symmetric positive definite P through its Cholesky factor L: L^-T L^-1. Returns 1
 * when P is not positive definite. */
HELPER int inv_spd(const double *P, double *out)
{
    double L[N * N] = {0.0}, Li[N * N] = {0.0};
    for (int j = 0; j < N; j++) {
        double d = P[j * N + j];
        for (int k = 0; k < j; k++)
            d -= L[j * N + k] * L[j * N + k];
        if (!(d > 0.0))
            return 1;
        L[j * N + j] = sqrt(d);
        for (int i = j + 1; i < N; i++) {
            double s = P[i * N + j];
            for (int k = 0; k < j; k++)
                s -= L[i * N + k] * L[j * N + k];
            L[i * N + j] = s / L[j * N + j];
        }
    }
    for (int c = 0; c < N; c++)  /* Li = L^-1, column by column (lower triangular) */
        for (int i = c; i < N; i++) {
            double s = i == c ? 1.0 : 0.0;
            for (int k = c; k < i; k++)
                s -= L[i * N + k] * Li[k * N + c];
            Li[i * N + c] = s / L[i * N + i];
        }
    for (int i = 0; i < N; i++)  /* (L^-T L^-1)_ij = sum over k >= i, j of Li_ki Li_kj: symmetric */
        for (int j = 0; j <= i; j++) {
            double s = 0.0;
            for (int k = i; k < N; k++)
                s = fma(Li[k * N + i], Li[k * N + j], s);
            out[i * N + j] = out[j * N + i] = s;
        }
    return 0;
}

/* One cycle's distributed-filter fusion (paper eqs. 3-4) of local estimates x1, x2 (15) with covariances P1, P2
 * (15 x 15): P4 = (P1^-1 + P2^-1)^-1 and x = P4 (P1^-1 x1 + P2^-1 x2); with the cross-covariance P12 (15 x 15;
 * NULL: none), the covariance of that estimate's error sym(W1 P1 W1^T + W2 P2 W2^T + C + C^T), C = W1 P12 W2^T,
 * W_i = P4 P_i^-1, into Pe (15 x 15), or, with Pe NULL, its diagonal alone into d (15) and no x (x NULL): the same
 * sums element by element, so d equals Pe's diagonal to the bit. Returns 1 when a covariance is not positive
 * definite. */
HELPER int fuse_one(const double *P1, const double *P2, const double *P12, const double *x1, const double *x2,
                    double *x, double *P, double *Pe, double *d)
{
    double I1[N * N], I2[N * N], Is[N * N], W1[N * N], W2[N * N], T[N * N], U[N * N], V[N * N];
    if (inv_spd(P1, I1) || inv_spd(P2, I2))
        return 1;
    for (int i = 0; i < N * N; i++)
        Is[i] = I1[i] + I2[i];
    if (inv_spd(Is, P))
        return 1;
    if (x) {
        double vec[N];
        for (int i = 0; i < N; i++) {
            double s = 0.0;
            for (int j = 0; j < N; j++)
                s = fma(I1[i * N + j], x1[j], s);
            for (int j = 0; j < N; j++)
                s = fma(I2[i * N + j], x2[j], s);
            vec[i] = s;
        }
        for (int i = 0; i < N; i++) {
            double s = 0.0;
            for (int j = 0; j < N; j++)
                s = fma(P[i * N + j], vec[j], s);
            x[i] = s;
        }
    }
    if (!P12)
        return 0;
    matmul(N, N, N, P, N, I1, N, 0, W1, N);
    matmul(N, N, N, P, N, I2, N, 0, W2, N);
    if (!Pe) {  /* the diagonals of the products below: row i of the left factor times row i of W_i */
        double u[N], c[N];
        matmul(N, N, N, W1, N, P1, N, 0, T, N);
        matmul(N, N, N, W2, N, P2, N, 0, U, N);
        matmul(N, N, N, W1, N, P12, N, 0, V, N);
        for (int i = 0; i < N; i++) {
            double s1 = 0.0, s2 = 0.0, s3 = 0.0;
            for (int l = 0; l < N; l++) {
                s1 = fma(T[i * N + l], W1[i * N + l], s1);
                s2 = fma(U[i * N + l], W2[i * N + l], s2);
                s3 = fma(V[i * N + l], W2[i * N + l], s3);
            }
            u[i] = s1 + s2;
            c[i] = s3;
        }
        for (int i = 0; i < N; i++) {
            const double t = u[i] + c[i] + c[i];
            d[i] = 0.5 * (t + t);
        }
        return 0;
    }
    matmul(N, N, N, W1, N, P1, N, 0, T, N);
    matmul(N, N, N, T, N, W1, N, 1, U, N);        /* W1 P1 W1^T */
    matmul(N, N, N, W2, N, P2, N, 0, T, N);
    matmul(N, N, N, T, N, W2, N, 1, V, N);        /* W2 P2 W2^T */
    for (int i = 0; i < N * N; i++)
        U[i] += V[i];
    matmul(N, N, N, W1, N, P12, N, 0, T, N);
    matmul(N, N, N, T, N, W2, N, 1, V, N);        /* C */
    for (int i = 0; i < N; i++)
        for (int j = 0; j < N; j++)
            T[i * N + j] = U[i * N + j] + V[i * N + j] + V[j * N + i];
    for (int i = 0; i < N; i++)
        for (int j = 0; j < N; j++)
            Pe[i * N + j] = 0.5 * (T[i * N + j] + T[j * N + i]);
    return 0;
}

/* The distributed filter's fusion (fuse_one) of m cycles' local estimates x1, x2 (m, 15) with covariances P1, P2
 * and cross-covariance P12 (m, 15, 15; NULL: none) into x (m, 15), P4 and Pe (m, 15, 15; Pe unused without P12).
 * Returns 1 when a covariance is not positive definite. */
KERNEL int32_t fieldlog_dkf_fuse(int64_t m, const double *P1, const double *P2, const double *P12, const double *x1,
                                 const double *x2, double *x, double *P4, double *Pe)
{
    for (int64_t k = 0; k < m; k++) {
        const size_t o = (size_t)k * N * N;
        if (fuse_one(P1 + o, P2 + o, P12 ? P12 + o : NULL, x1 + k * N, x2 + k * N, x + k * N, P4 + o,
                     P12 ? Pe + o : NULL, NULL))
            return 1;
    }
    return 0;
}

/* One local filter's state through the cycles, as kf.propagate_state: x (15) in place, its value after each of
 * the m cycles into hist at row stride ld; a zero state stays zero without a product */
HELPER void local_states(int64_t m, const double *Phi, double *x, double *hist, int ld)
{
    int any = 0;
    for (int i = 0; i < N; i++)
        any |= x[i] != 0.0;
    double y[N];
    for (int64_t k = 0; k < m; k++) {
        if (any) {
            matmul(N, N, 1, Phi + k * N * N, N, x, 1, 0, y, 1);
            memcpy(x, y, sizeof y);
        }
        memcpy(hist + k * ld, x, sizeof y);
    }
}

/* DistributedKF.propagate of the paper's fusion in one call: the local states x1, x2 (15) and covariances P1, P2
 * (15 x 15, q_scale Q added) and their cross-covariance P12 (Q added) through the m cycles Phi, Q (m, 15, 15), in
 * place, as kf.propagate_state and fieldlog_propagate_cov give them; xs (m, 2, 15) and hist (3, m, 15, 15) get
 * the states and P1, P2, P12 after each cycle; d (m, 15) the diagonal of the fused estimate's error covariance
 * after each (fuse_one); x (15), P4 and Pe (15 x 15) the whole fusion after the last. Returns 1 when a covariance
 * is not positive definite. */
KERNEL int32_t fieldlog_dkf_propagate(int64_t m, const double *Phi, const double *Q, double q_scale, double *x1,
                                      double *x2, double *P1, double *P2, double *P12, double *xs, double *hist,
                                      double *d, double *x, double *P4, double *Pe)
{
    const size_t s = (size_t)m * N * N;
    local_states(m, Phi, x1, xs, 2 * N);
    local_states(m, Phi, x2, xs + N, 2 * N);
    propagate_cov(m, Phi, Q, q_scale, 1, P1, hist);
    propagate_cov(m, Phi, Q, q_scale, 1, P2, hist + s);
    propagate_cov(m, Phi, Q, 1.0, 0, P12, hist + 2 * s);
    for (int64_t k = 0; k < m; k++) {
        const size_t o = (size_t)k * N * N;
        const double *p1 = hist + o, *p2 = hist + s + o, *p12 = hist + 2 * s + o, *y = xs + k * 2 * N;
        const int last = k == m - 1;
        if (fuse_one(p1, p2, p12, y, y + N, last ? x : NULL, P4, last ? Pe : NULL, d + k * N))
            return 1;
        if (last)
            for (int i = 0; i < N; i++)
                d[k * N + i] = Pe[i * N + i];
    }
    return 0;
}

/* The RTS backward pass (fusion/smoother.py rts) over the n records of one chunk, each `stride` bytes of
 * smoother.RECORD with its fields phi, pm, pp, dx, sm, sp at the byte offsets off[0..5] (sm, sp: 15 x 9).
 * `next`: the record after the chunk (NULL: the chunk ends the drive); Ps (15 x 15), Ss (15 x 9): its smoothed
 * covariance and consider sensitivity in, record 0's out. y (n + 1, 15): y[n] the next record's smoothed error
 * in, y[0..n) out; d (n, 15): the smoothed variances out. m_pred (n + 1, 15), m_upd (n, 15): the forward means
 * of a bridged run (NULL: none). var_c (9): the consider parameters' variances (NULL: none). For each record k,
 * from the last: C = (pm_{k+1}^-1 phi_{k+1} pp_k)^T, y_k = [m+_k +] C (y_{k+1} + dx_{k+1} [- m-_{k+1}]),
 * Ps_k = sym(pp_k + C (Ps_{k+1} - pm_{k+1}) C^T), Ss_k = sp_k + C (Ss_{k+1} - sm_{k+1}), in numpy's order.
 * Returns 1 when a predicted covariance is singular. */
KERNEL int32_t fieldlog_rts_chunk(int64_t n, const uint8_t *rec, int64_t stride, const int64_t *off,
                                  const uint8_t *next, double *Ps, double *Ss, const double *m_pred,
                                  const double *m_upd, const double *var_c, double *y, double *d)
{
    enum { NP = 9 };
    double A[N * N], X[N * N], C[N * N], D[N * N], CD[N * N], T[N * N], E[N * NP], v[N];
    for (int64_t k = n - 1; k >= 0; k--) {
        const uint8_t *r = rec + k * stride, *rn = k + 1 < n ? r + stride : next;
        const double *pp = (const double *)(r + off[2]), *sp = (const double *)(r + off[5]);
        double *yk = y + k * N;
        if (!rn) {
            memcpy(Ps, pp, sizeof(double) * N * N);
            memcpy(Ss, sp, sizeof(double) * N * NP);
            for (int i = 0; i < N; i++)
                yk[i] = m_upd ? m_upd[k * N + i] : 0.0;
        } else {
            const double *phi = (const double *)(rn + off[0]), *pm = (const double *)(rn + off[1]);
            const double *dx = (const double *)(rn + off[3]), *sm = (const double *)(rn + off[4]);
            matmul(N, N, N, phi, N, pp, N, 0, A, N);
            memcpy(X, pm, sizeof X);
            if (lu_solve(N, X, N, A))  /* A <- pm^-1 phi pp = C^T */
                return 1;
            for (int i = 0; i < N; i++)
                for (int j = 0; j < N; j++)
                    C[i * N + j] = A[j * N + i];
            for (int i = 0; i < N; i++)
                v[i] = m_pred ? (yk[N + i] + dx[i]) - m_pred[(k + 1) * N + i] : yk[N + i] + dx[i];
            for (int i = 0; i < N; i++) {
                double s = 0.0;
                for (int j = 0; j < N; j++)
                    s = fma(C[i * N + j], v[j], s);
                yk[i] = m_upd ? m_upd[k * N + i] + s : s;
            }
            for (int i = 0; i < N * N; i++)
                D[i] = Ps[i] - pm[i];
            matmul(N, N, N, C, N, D, N, 0, CD, N);
            matmul(N, N, N, CD, N, C, N, 1, T, N);
            sym_of_sum(pp, T, T, Ps);
            for (int i = 0; i < N * NP; i++)
                E[i] = Ss[i] - sm[i];
            matmul(N, N, NP, C, N, E, NP, 0, T, NP);
            for (int i = 0; i < N * NP; i++)
                Ss[i] = sp[i] + T[i];
        }
        for (int i = 0; i < N; i++)
            d[k * N + i] = Ps[i * N + i];
        if (var_c)
            for (int i = 12; i < 15; i++) {  /* BA: ((Ss * Ss) @ var_c)[BA] */
                double s = 0.0;
                for (int j = 0; j < NP; j++)
                    s = fma(Ss[i * NP + j] * Ss[i * NP + j], var_c[j], s);
                d[k * N + i] += s;
            }
    }
    return 0;
}

/* predictors.Rls.update over m rows in turn: weights w (n) and matrix P (n x n) in place, each row phi (n) of
 * Phi (m x n) with its target y: Pphi = P phi, k = Pphi / (forget + phi . Pphi), w += k (y - phi . w),
 * P <- sym((P - k Pphi^T) / forget), in numpy's order. */
KERNEL void fieldlog_rls_update(int64_t m, int64_t n, double *P, double *w, const double *Phi, const double *y,
                                double forget)
{
    const int nn = (int)n;
    double Pphi[nn > 0 ? nn : 1], k[nn > 0 ? nn : 1];
    for (int64_t r = 0; r < m; r++) {
        const double *phi = Phi + r * nn;
        double den = 0.0, pred = 0.0;
        for (int i = 0; i < nn; i++) {
            double s = 0.0;
            for (int j = 0; j < nn; j++)
                s = fma(P[i * nn + j], phi[j], s);
            Pphi[i] = s;
        }
        for (int i = 0; i < nn; i++)
            den = fma(phi[i], Pphi[i], den);
        den = forget + den;
        for (int i = 0; i < nn; i++) {
            k[i] = Pphi[i] / den;
            pred = fma(phi[i], w[i], pred);
        }
        const double e = y[r] - pred;
        for (int i = 0; i < nn; i++)
            w[i] = w[i] + k[i] * e;
        for (int i = 0; i < nn; i++)
            for (int j = 0; j < nn; j++)
                P[i * nn + j] = (P[i * nn + j] - k[i] * Pphi[j]) / forget;
        for (int i = 0; i < nn; i++)
            for (int j = 0; j < i; j++)
                P[i * nn + j] = P[j * nn + i] = 0.5 * (P[i * nn + j] + P[j * nn + i]);
    }
}
