/* Cone crusher with Whiten's classification function (Whiten 1972, "The
 * simulation of crushing plants"; Napier-Munn et al. 1996, Mineral
 * Comminution Circuits, ch. 6), with the same interface as the jaw crusher.
 *
 *   C(d) = 0                           for d <= K1   (K1 = gap_width, closed side setting)
 *        = 1 - ((K2 - d)/(K2 - K1))^K3 for K1 < d < K2 (K2 = open_side_width, K3 = whiten_exponent)
 *        = 1                           for d >= K2
 *
 * Material selected for breakage (fraction C of each class) breaks with the
 * breakage function B (broken mass spread uniformly over the finer classes,
 * as in the jaw crusher and the mill) and returns to the crushing zone until
 * it passes unselected. Per unit feed the internal flow x solves
 * x = f + B C x and the product is p = (I - C) x, so the fragmentation map is
 * M = (I - C)(I - B C)^-1, computed column by column by back-substitution
 * from the coarsest class (B moves mass only to finer classes). Class 0
 * cannot break, so C(d_0) is taken as 0.
 *
 * Torque: tau = sum_k (k_undersize + (k_oversize - k_undersize) C(d_k)) M^k,
 * the jaw crusher's eq. (crusher_torque) with the hard oversize step replaced
 * by the classification function; P = tau omega; energy integrated. */
#include <math.h>
#include <stdio.h>

#include "model.h"

#define N_CLASSES 16

/* d_k = 1e-5 m * r^k, r = 10^(1/3) (cosim/sizes.py), tabulated on first use */
static double class_diameter(int k) {
    static double diameters[N_CLASSES];
    static int tabulated = 0;
    if (!tabulated) {
        for (int i = 0; i < N_CLASSES; i++) diameters[i] = 1e-5 * pow(pow(10.0, 1.0 / 3.0), i);
        tabulated = 1;
    }
    return diameters[k];
}

static double classification(const double *v, int k) {
    double d = class_diameter(k), k1 = v[V_gap_width], k2 = v[V_open_side_width];
    if (k == 0 || d <= k1) return 0.0;
    if (d >= k2) return 1.0;
    return 1.0 - pow((k2 - d) / (k2 - k1), v[V_whiten_exponent]);
}

static double crusher_torque(const double *v) {
    double torque = 0.0;
    for (int k = 0; k < N_CLASSES; k++) {
        double coefficient = v[V_k_undersize] + (v[V_k_oversize] - v[V_k_undersize]) * classification(v, k);
        torque += coefficient * v[V_zone_hardness_mass + k];
    }
    return torque;
}

int model_check_parameters(const double *v, char *message, size_t size) {
    if (v[V_open_side_width] <= v[V_gap_width]) {
        snprintf(message, size, "open_side_width = %g m: must be > gap_width = %g m",
                 v[V_open_side_width], v[V_gap_width]);
        return 1;
    }
    return 0;
}

void model_initialize(double *v) { v[V_energy] = 0.0; }

void model_outputs(double *v) {
    double c[N_CLASSES];
    for (int k = 0; k < N_CLASSES; k++) c[k] = classification(v, k);
    v[V_torque] = crusher_torque(v);
    v[V_power] = v[V_torque] * v[V_speed];
    double *map = v + V_fragmentation_map;
    for (int j = 0; j < N_CLASSES; j++) {
        /* internal flow x for a unit feed into class j: x_i = e_ij + sum_{k > i} B[i][k] c_k x_k,
         * with B[i][k] = 1/k for i < k (uniform over the k finer classes) */
        double x[N_CLASSES];
        double broken_into_finer = 0.0; /* sum_{k > i} c_k x_k / k, accumulated from the top */
        for (int i = N_CLASSES - 1; i >= 0; i--) {
            x[i] = (i == j ? 1.0 : 0.0) + broken_into_finer;
            if (i > 0) broken_into_finer += c[i] * x[i] / i;
        }
        for (int i = 0; i < N_CLASSES; i++) map[i * N_CLASSES + j] = (1.0 - c[i]) * x[i];
    }
}

void model_advance(double *v, double h) { v[V_energy] += crusher_torque(v) * v[V_speed] * h; }
