/* Stair counter test model: counter = increment * floor(time); the FMU
 * requests the end of the simulation when its time reaches stop_time (an FMI 3
 * doStep with terminateSimulation, an FMI 2 fmi2Discard with fmi2Terminated),
 * after advancing exactly to stop_time. */
#include <math.h>
#include <stdio.h>

#include "typed_model.h"

int model_check(const ModelData *m, char *message, size_t size) {
    if (!(m->stop_time > 0.0) || !isfinite(m->stop_time)) {
        snprintf(message, size, "stop_time = %g s: must be finite and > 0 s", m->stop_time);
        return 1;
    }
    return 0;
}

void model_outputs(ModelData *m) {
    m->counter = m->increment * (int32_t)floor(m->time);
    m->elapsed = m->time;
}

StepResult model_advance(ModelData *m, double end, int stop_at_events) {
    (void)stop_at_events;
    if (end >= m->stop_time) {
        m->time = m->stop_time;
        return STEP_TERMINATE;
    }
    m->time = end;
    return STEP_COMPLETE;
}

int model_event_update(ModelData *m) { return m->time >= m->stop_time; }
