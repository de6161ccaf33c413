/* The strapdown INS step of fusion/ins.py (its module docstring gives the algorithm, units and frames), in C.
 *
 * Built with the package (setup.py) and called through ctypes by ins.integrate; it needs no
 * Python headers. Compiled without floating-point contraction (-ffp-contract=off) and evaluated in the order
 * the Python source of the algorithm writes it, so the results are the same to the bit on every machine with
 * IEEE-754 doubles and the same libm. The Earth constants come from fusion/earth.py, passed in by the caller
 * (EARTH_* below), so they have one definition.
 *
 * Vectors are ENU (navigation) or RFU (body) triples; quaternions [x, y, z, w] of C_bn.
 */
#include <math.h>
#include <stdint.h>

enum { EARTH_A, EARTH_E2, EARTH_F, EARTH_M, EARTH_K, EARTH_GAMMA_E, EARTH_OMEGA_IE, EARTH_N };

static void cross(const double a[3], const double b[3], double out[3])
{
    double x = a[1] * b[2] - a[2] * b[1], y = a[2] * b[0] - a[0] * b[2], z = a[0] * b[1] - a[1] * b[0];
    out[0] = x;
    out[1] = y;
    out[2] = z;
}

static void quat_mul(const double p[4], const double q[4], double out[4])
{
    double px = p[0], py = p[1], pz = p[2], pw = p[3], qx = q[0], qy = q[1], qz = q[2], qw = q[3];
    out[0] = pw * qx + qw * px + py * qz - pz * qy;
    out[1] = pw * qy + qw * py + pz * qx - px * qz;
    out[2] = pw * qz + qw * pz + px * qy - py * qx;
    out[3] = pw * qw - px * qx - py * qy - pz * qz;
}

/* the quaternion of rotation vector r (rad) */
static void rotvec_quat(const double r[3], double out[4])
{
    double a2 = r[0] * r[0] + r[1] * r[1] + r[2] * r[2];
    double a = sqrt(a2), k;
    if (a < 1e-4)
        k = 0.5 - a2 / 48.0 + a2 * a2 / 3840.0;
    else
        k = sin(0.5 * a) / a;
    out[0] = k * r[0];
    out[1] = k * r[1];
    out[2] = k * r[2];
    out[3] = cos(0.5 * a);
}

/* C(q) v for a unit quaternion q */
static void rotate(const double q[4], const double v[3], double out[3])
{
    double t[3], c[3];
    cross(q, v, t);
    t[0] = 2.0 * t[0];
    t[1] = 2.0 * t[1];
    t[2] = 2.0 * t[2];
    cross(q, t, c);
    double w = q[3];
    out[0] = v[0] + w * t[0] + c[0];
    out[1] = v[1] + w * t[1] + c[1];
    out[2] = v[2] + w * t[2] + c[2];
}

/* (R_M + h, R_N + h), m: earth.principal_radii; s the sine of the latitude */
static void radii(const double *e, double s, double h, double *rm, double *rn)
{
    double s2 = s * s;
    double w = sqrt(1.0 - e[EARTH_E2] * s2);
    double r_n = e[EARTH_A] / w;
    double r_m = r_n * (1.0 - e[EARTH_E2]) / (w * w);
    *rm = r_m + h;
    *rn = r_n + h;
}

/* normal gravity, m/s^2: earth.gravity; s the sine of the latitude */
static double gravity(const double *e, double s, double h)
{
    double a = e[EARTH_A], f = e[EARTH_F], s2 = s * s;
    double g0 = e[EARTH_GAMMA_E] * (1.0 + e[EARTH_K] * s2) / sqrt(1.0 - e[EARTH_E2] * s2);
    return g0 * (1.0 - 2.0 / a * (1.0 + f + e[EARTH_M] - 2.0 * f * s2) * h + 3.0 * h * h / (a * a));
}

/* one step of dt s from samples 0 (w0 rad/s, f0 m/s^2) to 1; p = lat, lon, h, v_n[3], q[4] updated in place */
static void step(const double *e, double dt, const double w0[3], const double f0[3], const double w1[3],
                 const double f1[3], double p[10])
{
    const double lat = p[0], lon = p[1], h = p[2], *v = p + 3, *q = p + 6;
    double dt2 = dt * dt / 12.0, dth[3], dv[3], con[3], phi[3], rot[3], s1[3], s2[3], dv_b[3], dv_n0[3];
    double q_b[4], q_n[4], q_m[4], q1[4];
    for (int i = 0; i < 3; i++) {
        dth[i] = 0.5 * (w0[i] + w1[i]) * dt;
        dv[i] = 0.5 * (f0[i] + f1[i]) * dt;
    }
    cross(w0, w1, con);
    for (int i = 0; i < 3; i++)
        phi[i] = dth[i] + dt2 * con[i];
    cross(dth, dv, rot);
    cross(w0, f1, s1);
    cross(f0, w1, s2);
    for (int i = 0; i < 3; i++)
        dv_b[i] = dv[i] + 0.5 * rot[i] + dt2 * (s1[i] + s2[i]);
    rotate(q, dv_b, dv_n0);
    rotvec_quat(phi, q_b);

    double lat_m = lat, h_m = h, v_m[3] = {v[0], v[1], v[2]};
    double lat1 = lat, lon1 = lon, h1 = h, v1[3] = {v[0], v[1], v[2]}, zeta[3] = {0.0, 0.0, 0.0};
    for (int pass = 0; pass < 2; pass++) {
        double rm, rn, sl = sin(lat_m), cl = cos(lat_m);
        radii(e, sl, h_m, &rm, &rn);
        double w_ie[3] = {0.0, e[EARTH_OMEGA_IE] * cl, e[EARTH_OMEGA_IE] * sl};
        double w_en[3] = {-v_m[1] / rm, v_m[0] / rn, v_m[0] * sl / cl / rn};
        double zr[3], cor[3], w2[3];
        for (int i = 0; i < 3; i++) {
            zeta[i] = (w_ie[i] + w_en[i]) * dt;
            w2[i] = 2.0 * w_ie[i] + w_en[i];
        }
        cross(zeta, dv_n0, zr);
        cross(w2, v_m, cor);
        double g = gravity(e, sl, h_m);
        v1[0] = v[0] + dv_n0[0] - 0.5 * zr[0] - cor[0] * dt;
        v1[1] = v[1] + dv_n0[1] - 0.5 * zr[1] - cor[1] * dt;
        v1[2] = v[2] + dv_n0[2] - 0.5 * zr[2] + (-g - cor[2]) * dt;
        for (int i = 0; i < 3; i++)
            v_m[i] = 0.5 * (v[i] + v1[i]);
        lat1 = lat + v_m[1] / rm * dt;
        lon1 = lon + v_m[0] / (rn * cl) * dt;
        h1 = h + v_m[2] * dt;
        lat_m = 0.5 * (lat + lat1);
        h_m = 0.5 * (h + h1);
    }

    double mzeta[3] = {-zeta[0], -zeta[1], -zeta[2]};
    rotvec_quat(mzeta, q_n);
    quat_mul(q, q_b, q_m);
    quat_mul(q_n, q_m, q1);
    double nq = sqrt(q1[0] * q1[0] + q1[1] * q1[1] + q1[2] * q1[2] + q1[3] * q1[3]);
    if (q1[3] < 0.0)
        nq = -nq;
    p[0] = lat1;
    p[1] = lon1;
    p[2] = h1;
    for (int i = 0; i < 3; i++)
        p[3 + i] = v1[i];
    for (int i = 0; i < 4; i++)
        p[6 + i] = q1[i] / nq;
}

/* The INS over n samples at times t (s), rates w (n x 3, rad/s) and specific forces f (n x 3, m/s^2), from the
 * state p0 = lat, lon (rad), h (m), v_n[3] (m/s), q[4] at t[0]; e: the Earth constants (EARTH_*). Element k
 * of lat, lon, h (n), v (n x 3) and q (n x 4) is the state at t[k]; element 0 is p0's. Returns 1, having
 * written nothing, when the times are not strictly increasing (a NaN among them included); else 0. */
int32_t fieldlog_ins_integrate(int64_t n, const double *t, const double *w, const double *f, const double *e,
                               const double *p0, double *lat, double *lon, double *h, double *v, double *q)
{
    for (int64_t k = 1; k < n; k++)
        if (!(t[k] > t[k - 1]))
            return 1;
    double p[10];
    for (int i = 0; i < 10; i++)
        p[i] = p0[i];
    for (int64_t k = 0; k < n; k++) {
        if (k > 0)
            step(e, t[k] - t[k - 1], w + 3 * (k - 1), f + 3 * (k - 1), w + 3 * k, f + 3 * k, p);
        lat[k] = p[0];
        lon[k] = p[1];
        h[k] = p[2];
        for (int i = 0; i < 3; i++)
            v[3 * k + i] = p[3 + i];
        for (int i = 0; i < 4; i++)
            q[4 * k + i] = p[6 + i];
    }
    return 0;
}
