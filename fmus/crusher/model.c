/* Jaw crusher model: paper section "Simulator", eq. (crusher_torque).
 *
 *   tau_cr = sum_k k_cr^k M^k,  M^k = sum_{n in crusher zone} m_n h_n f_n^k  (input zone_hardness_mass)
 *   k_cr^k = k_oversize (1.0 N m/kg) if d_k >= d_cr else k_undersize (0.1 N m/kg)
 *   P_cr = tau_cr omega_cr,  energy = integral of P_cr dt (exact for inputs held over a step)
 *
 * Fragmentation map (paper: f_n := f_n - df_n- + df_n+): the oversize
 * fractions (d_k >= d_cr) break into a uniform distribution over the n_d
 * undersize classes, so M[i][j] = 1/n_d for j oversize and i undersize, and
 * M[j][j] = 1 for j undersize. Columns sum to 1 (mass-conserving).
 * Class diameters d_k = 1e-5 m * 10^(k/3) (cosim/sizes.py). */
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

static int is_oversize(const double *v, int k) { return class_diameter(k) >= v[V_gap_width]; }

static double crusher_torque(const double *v) {
    double torque = 0.0;
    for (int k = 0; k < N_CLASSES; k++)
        torque += (is_oversize(v, k) ? v[V_k_oversize] : v[V_k_undersize]) * v[V_zone_hardness_mass + k];
    return torque;
}

int model_check_parameters(const double *v, char *message, size_t size) {
    if (v[V_gap_width] <= class_diameter(0)) {
        snprintf(message, size, "gap_width = %g m: must be > d_0 = %g m (at least one undersize class)",
                 v[V_gap_width], class_diameter(0));
        return 1;
    }
    return 0;
}

void model_initialize(double *v) { v[V_energy] = 0.0; }

void model_outputs(double *v) {
    int n_undersize = 0;
    for (int k = 0; k < N_CLASSES; k++) n_undersize += !is_oversize(v, k);
    v[V_torque] = crusher_torque(v);
    v[V_power] = v[V_torque] * v[V_speed];
    double *map = v + V_fragmentation_map;
    for (int i = 0; i < N_CLASSES; i++)
        for (int j = 0; j < N_CLASSES; j++) {
            double m;
            if (is_oversize(v, j))
                m = is_oversize(v, i) ? 0.0 : 1.0 / n_undersize;
            else
                m = (i == j) ? 1.0 : 0.0;
            map[i * N_CLASSES + j] = m;
        }
}

void model_advance(double *v, double h) { v[V_energy] += crusher_torque(v) * v[V_speed] * h; }
