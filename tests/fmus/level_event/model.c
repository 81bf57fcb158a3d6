/* Level-reset test model: d level/dt = rate (held over a step); when the
 * level reaches threshold (time t_e = t + (threshold - level) / rate, exact
 * for a held rate) an event resets it to 0 and counts it. In FMI 3 event mode
 * with early return the FMU returns from doStep at t_e and the importer runs
 * the event update; otherwise (and in FMI 2) the FMU applies the same update
 * at t_e inside doStep, with the same arithmetic. */
#include <math.h>
#include <stdio.h>

#include "typed_model.h"

/* The level lives in the output slot (a state reported as it is). */
int model_check(const ModelData *m, char *message, size_t size) {
    if (!(m->threshold > 0.0) || !isfinite(m->threshold)) {
        snprintf(message, size, "threshold = %g m: must be finite and > 0 m", m->threshold);
        return 1;
    }
    return 0;
}

void model_outputs(ModelData *m) { (void)m; }

StepResult model_advance(ModelData *m, double end, int stop_at_events) {
    while (m->rate > 0.0) {
        double t_event = m->time + (m->threshold - m->level) / m->rate;
        if (t_event > end) break;
        m->time = t_event;
        m->level = m->threshold;
        if (stop_at_events) return STEP_EVENT;
        model_event_update(m);
    }
    m->level += m->rate * (end - m->time);
    m->time = end;
    return STEP_COMPLETE;
}

int model_event_update(ModelData *m) {
    if (m->level >= m->threshold) {
        m->level = 0.0;
        m->resets += 1;
    }
    return 0;
}
