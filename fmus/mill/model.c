/* Grinding mill model: paper section "Simulator" (idealised mill after
 * Araker 2020), with the errata listed in fmus/README.md.
 *
 * Charge: c^k = charge_mass[k] [kg], m_gr = sum_k c^k, m_tot = m0 + m_gr,
 * m_gr-a = sum_{d_k >= d_gr-a} c^k (relative tolerance 1e-9, so d_gr-a = 1 mm
 * selects 0-based classes 6..15).
 * Speed: first-order response to the setpoint, d omega/dt = (setpoint - omega)/T,
 * integrated exactly over a step with the setpoint held.
 * Torques:  tau_gr-dr = mu_dr m_tot g r_mill
 *           tau_acc   = m_tot r_mill^2 d omega/dt
 *           tau_gr-a  = mu_gr-a m_gr g r_mill,
 *           mu_gr-a   = k_gr-a Theta(omega/omega_crit) m_gr-a omega / (m_gr omega_crit),
 *           Theta(x)  = Re sqrt(1 - x^4)
 *           tau_gr = tau_gr-dr + tau_acc + tau_gr-a,  P_gr = tau_gr omega.
 * Breakage rate of class k for hardness 1 (a particle of hardness h breaks at P^k / h):
 *   P^k = k_gr E_imp^k / E_brk^k (tau_gr-a omega / (tau0_gr-dr omega_crit))^2,
 *   E_imp^k = E_inf (e - exp(1 - D50/d_k)) d_k/d_gr,
 *   E_brk^k = E0_brk / (1 + (d_k/d_gr)^(1/4)),
 *   tau0_gr-dr = mu_dr m0 g r_mill (drive friction of the empty mill; erratum:
 *   the normalisation is tau0_gr-dr omega_crit), D50 the median size of the
 *   charge (0 for an empty mill). Class 0 has no finer class: P^0 = 0.
 * Daughter fractions (erratum: the printed redistribution is not
 * mass-conserving): mass broken out of class j goes uniformly to the j finer
 * classes, D[i][j] = 1/j for i < j, else 0.
 * Classifier: Q^k = k_esc / (1 + exp(k_cl (d_k/d_cl - 1))). */
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

/* median size: passing curve interpolated linearly in log(d) between class
 * edges (the same rule as cosim.sizes.d_passing) */
static double median_size(const double *mass) {
    double cumulative[N_CLASSES + 1], log_edges[N_CLASSES + 1];
    cumulative[0] = 0.0;
    log_edges[0] = log(class_diameter(0) / pow(10.0, 1.0 / 3.0));
    for (int k = 0; k < N_CLASSES; k++) {
        cumulative[k + 1] = cumulative[k] + mass[k];
        log_edges[k + 1] = log(class_diameter(k));
    }
    if (cumulative[N_CLASSES] <= 0.0) return 0.0;
    double target = 0.5 * cumulative[N_CLASSES];
    int j = 0;
    for (int k = 0; k <= N_CLASSES; k++) j += cumulative[k] < target;
    if (j < 1) j = 1;
    if (j > N_CLASSES) j = N_CLASSES;
    double width = cumulative[j] - cumulative[j - 1];
    double w = width > 0.0 ? (target - cumulative[j - 1]) / width : 0.0;
    if (w < 0.0) w = 0.0;
    if (w > 1.0) w = 1.0;
    return exp(log_edges[j - 1] + w * (log_edges[j] - log_edges[j - 1]));
}

static double theta(double x) {
    double y = 1.0 - x * x * x * x;
    return y > 0.0 ? sqrt(y) : 0.0;
}

int model_check_parameters(const double *v, char *message, size_t size) {
    double tau0 = v[V_mu_dr] * v[V_m0] * v[V_g] * v[V_r_mill];
    if (!(tau0 > 0.0)) {
        snprintf(message, size,
                 "mu_dr * m0 * g * r_mill = %g N m: must be > 0 (the empty-mill drive torque normalises breakage)",
                 tau0);
        return 1;
    }
    return 0;
}

void model_initialize(double *v) { v[V_speed] = v[V_initial_speed]; }

void model_outputs(double *v) {
    const double *charge = v + V_charge_mass;
    double omega = v[V_speed], omega_crit = v[V_omega_crit], g = v[V_g], r = v[V_r_mill];
    double m_gr = 0.0, m_active = 0.0;
    for (int k = 0; k < N_CLASSES; k++) {
        m_gr += charge[k];
        if (class_diameter(k) >= v[V_d_gr_a] * (1.0 - 1e-9)) m_active += charge[k];
    }
    double m_tot = v[V_m0] + m_gr;
    double acceleration = (v[V_speed_setpoint] - omega) / v[V_speed_time_constant];
    double torque_active = v[V_k_gr_a] * theta(omega / omega_crit) * m_active * omega / omega_crit * g * r;
    v[V_torque_drive] = v[V_mu_dr] * m_tot * g * r;
    v[V_torque_acceleration] = m_tot * r * r * acceleration;
    v[V_torque_active] = torque_active;
    v[V_torque] = v[V_torque_drive] + v[V_torque_acceleration] + torque_active;
    v[V_power] = v[V_torque] * omega;
    double d50 = median_size(charge);
    v[V_d50] = d50;

    double tau0 = v[V_mu_dr] * v[V_m0] * g * r;
    double activity = torque_active * omega / (tau0 * omega_crit);
    activity *= activity;
    for (int k = 0; k < N_CLASSES; k++) {
        double d = class_diameter(k), x = d / v[V_d_gr];
        double impact = v[V_impact_energy] * (exp(1.0) - exp(1.0 - d50 / d)) * x;
        double breakage = v[V_breakage_energy] / (1.0 + pow(x, 0.25));
        v[V_breakage_rate + k] = k == 0 ? 0.0 : v[V_k_gr] * impact / breakage * activity;
        v[V_escape_rate + k] = v[V_k_esc] / (1.0 + exp(v[V_k_cl] * (d / v[V_d_cl] - 1.0)));
        for (int j = 0; j < N_CLASSES; j++)
            v[V_daughter_fraction + k * N_CLASSES + j] = k < j ? 1.0 / j : 0.0;
    }
}

void model_advance(double *v, double h) {
    double setpoint = v[V_speed_setpoint];
    v[V_speed] = setpoint + (v[V_speed] - setpoint) * exp(-h / v[V_speed_time_constant]);
}
