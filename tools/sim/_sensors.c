/* The two recursions of tools/sim/sensors.py's noise models, in C (its docstrings give them), built with the
 * package (setup.py) and called through ctypes. Compiled without floating-point contraction and evaluated in the
 * written order, so a seed gives the same drive to the bit on every machine. Arrays are C-ordered float64. */
#include <math.h>
#include <stdint.h>

/* x[0] = z[0]; x[k] = phi[k-1] x[k-1] + sqrt(1 - phi[k-1]^2) z[k], rows of m, k < n (gauss_markov) */
void fieldlog_gm_recursion(int64_t n, int64_t m, const double *phi, const double *z, double *x)
{
    for (int64_t c = 0; c < m && n > 0; c++)
        x[c] = z[c];
    for (int64_t k = 1; k < n; k++) {
        double a = phi[k - 1], b = sqrt(1.0 - a * a);
        for (int64_t c = 0; c < m; c++)
            x[k * m + c] = a * x[(k - 1) * m + c] + b * z[k * m + c];
    }
}

/* y_k = b0 z_k + phi y_{k-1} down each column of z (n x m), y_{-1} = y_prev (m): the operations of
 * scipy.signal.lfilter([b0], [1, -phi], z, axis=0, zi=phi * y_prev), in its order (_ar1) */
void fieldlog_ar1(int64_t n, int64_t m, double b0, double phi, const double *z, const double *y_prev, double *y)
{
    for (int64_t c = 0; c < m; c++) {
        double state = phi * y_prev[c];
        for (int64_t k = 0; k < n; k++) {
            double yk = state + b0 * z[k * m + c];
            y[k * m + c] = yk;
            state = 0.0 * z[k * m + c] - yk * -phi;
        }
    }
}
