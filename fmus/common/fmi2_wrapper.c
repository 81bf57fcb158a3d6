/* FMI 2.0 Co-Simulation wrapper around one model source (see model.h).
 * Every array element is a scalar Real variable named name[i] or name[i,j]
 * (1-based, the Modelica convention); its value reference is its flat index
 * in v. Supports get/set/serialize FMU state; every other FMI 2.0 function is
 * exported and returns fmi2Error with a log message. */
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi2Functions.h"
#include "model.h"

typedef enum { MODE_INSTANTIATED, MODE_INITIALIZATION, MODE_STEP, MODE_TERMINATED } Mode;

typedef struct {
    double v[N_VALUES];
    double time;
    Mode mode;
    int outputs_stale;
    int logging_on;
    char *name;
    fmi2CallbackFunctions callbacks;
} Instance;

typedef struct {
    double v[N_VALUES];
    double time;
    Mode mode;
} SavedState;

static void log_error(Instance *instance, const char *format, ...) {
    char message[1024];
    va_list args;
    va_start(args, format);
    vsnprintf(message, sizeof message, format, args);
    va_end(args);
    if (instance && instance->callbacks.logger)
        instance->callbacks.logger(instance->callbacks.componentEnvironment, instance->name,
                                   fmi2Error, "logStatusError", "%s", message);
}

static fmi2Status unsupported(fmi2Component c, const char *function) {
    log_error((Instance *)c, "%s is not supported by %s", function, MODEL_IDENTIFIER);
    return fmi2Error;
}

static int check_values(Instance *instance, int causality) {
    for (int k = 0; k < N_VALUES; k++) {
        int var = VALUE_VARIABLE[k];
        if (VARIABLE_CAUSALITY[var] != causality) continue;
        double x = instance->v[k];
        if (!isfinite(x) || x < VARIABLE_MIN[var]) {
            if (VARIABLE_SIZE[var] > 1)
                log_error(instance, "%s[%d] (0-based) = %g: must be finite and >= %g %s",
                          VARIABLE_NAME[var], k - VARIABLE_OFFSET[var], x, VARIABLE_MIN[var],
                          VARIABLE_UNIT[var]);
            else
                log_error(instance, "%s = %g: must be finite and >= %g %s", VARIABLE_NAME[var], x,
                          VARIABLE_MIN[var], VARIABLE_UNIT[var]);
            return 1;
        }
    }
    return 0;
}

static void refresh_outputs(Instance *instance) {
    if (instance->outputs_stale) {
        model_outputs(instance->v);
        instance->outputs_stale = 0;
    }
}

const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }
const char *fmi2GetVersion(void) { return fmi2Version; }

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean loggingOn, size_t nCategories,
                               const fmi2String categories[]) {
    (void)nCategories; (void)categories;
    ((Instance *)c)->logging_on = loggingOn;
    return fmi2OK;
}

fmi2Component fmi2Instantiate(fmi2String instanceName, fmi2Type fmuType, fmi2String fmuGUID,
                              fmi2String fmuResourceLocation,
                              const fmi2CallbackFunctions *functions, fmi2Boolean visible,
                              fmi2Boolean loggingOn) {
    (void)fmuResourceLocation; (void)visible;
    const char *name = instanceName ? instanceName : MODEL_IDENTIFIER;
    if (fmuType != fmi2CoSimulation || !fmuGUID || strcmp(fmuGUID, INSTANTIATION_TOKEN) != 0) {
        if (functions && functions->logger)
            functions->logger(functions->componentEnvironment, name, fmi2Error, "logStatusError",
                              "%s", fmuType != fmi2CoSimulation
                                        ? MODEL_IDENTIFIER " supports Co-Simulation only"
                                        : "GUID does not match this binary of " MODEL_IDENTIFIER);
        return NULL;
    }
    Instance *instance = calloc(1, sizeof(Instance));
    if (!instance) return NULL;
    instance->name = malloc(strlen(name) + 1);
    if (instance->name) strcpy(instance->name, name);
    if (functions) instance->callbacks = *functions;
    memcpy(instance->v, START_VALUES, sizeof instance->v);
    instance->mode = MODE_INSTANTIATED;
    instance->outputs_stale = 1;
    instance->logging_on = loggingOn;
    return instance;
}

void fmi2FreeInstance(fmi2Component c) {
    if (!c) return;
    free(((Instance *)c)->name);
    free(c);
}

fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean toleranceDefined, fmi2Real tolerance,
                               fmi2Real startTime, fmi2Boolean stopTimeDefined, fmi2Real stopTime) {
    (void)toleranceDefined; (void)tolerance; (void)stopTimeDefined; (void)stopTime;
    ((Instance *)c)->time = startTime;
    return fmi2OK;
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c) {
    ((Instance *)c)->mode = MODE_INITIALIZATION;
    return fmi2OK;
}

fmi2Status fmi2ExitInitializationMode(fmi2Component c) {
    Instance *self = (Instance *)c;
    char message[512];
    if (check_values(self, CAUSALITY_PARAMETER)) return fmi2Error;
    if (model_check_parameters(self->v, message, sizeof message)) {
        log_error(self, "%s", message);
        return fmi2Error;
    }
    if (check_values(self, CAUSALITY_INPUT)) return fmi2Error;
    model_initialize(self->v);
    model_outputs(self->v);
    self->outputs_stale = 0;
    self->mode = MODE_STEP;
    return fmi2OK;
}

fmi2Status fmi2Terminate(fmi2Component c) {
    ((Instance *)c)->mode = MODE_TERMINATED;
    return fmi2OK;
}

fmi2Status fmi2Reset(fmi2Component c) {
    Instance *self = (Instance *)c;
    memcpy(self->v, START_VALUES, sizeof self->v);
    self->time = 0.0;
    self->mode = MODE_INSTANTIATED;
    self->outputs_stale = 1;
    return fmi2OK;
}

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                       fmi2Real value[]) {
    Instance *self = (Instance *)c;
    if (self->mode == MODE_STEP || self->mode == MODE_INITIALIZATION) refresh_outputs(self);
    for (size_t i = 0; i < nvr; i++) {
        if (vr[i] >= N_VALUES) {
            log_error(self, "fmi2GetReal: unknown value reference %u", vr[i]);
            return fmi2Error;
        }
        value[i] = self->v[vr[i]];
    }
    return fmi2OK;
}

fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                       const fmi2Real value[]) {
    Instance *self = (Instance *)c;
    for (size_t i = 0; i < nvr; i++) {
        if (vr[i] >= N_VALUES) {
            log_error(self, "fmi2SetReal: unknown value reference %u", vr[i]);
            return fmi2Error;
        }
        int var = VALUE_VARIABLE[vr[i]];
        int causality = VARIABLE_CAUSALITY[var];
        if (causality == CAUSALITY_OUTPUT ||
            (causality == CAUSALITY_PARAMETER && self->mode == MODE_STEP)) {
            log_error(self, "fmi2SetReal: %s (%s) cannot be set now", VARIABLE_NAME[var],
                      causality == CAUSALITY_OUTPUT ? "an output" : "a fixed parameter");
            return fmi2Error;
        }
        self->v[vr[i]] = value[i];
    }
    self->outputs_stale = 1;
    return fmi2OK;
}

fmi2Status fmi2DoStep(fmi2Component c, fmi2Real currentCommunicationPoint,
                      fmi2Real communicationStepSize, fmi2Boolean noSetFMUStatePriorToCurrentPoint) {
    (void)currentCommunicationPoint; (void)noSetFMUStatePriorToCurrentPoint;
    Instance *self = (Instance *)c;
    if (self->mode != MODE_STEP) {
        log_error(self, "fmi2DoStep called outside step mode");
        return fmi2Error;
    }
    if (!(communicationStepSize > 0.0) || !isfinite(communicationStepSize)) {
        log_error(self, "communicationStepSize = %g: must be finite and > 0 s", communicationStepSize);
        return fmi2Error;
    }
    if (check_values(self, CAUSALITY_INPUT)) return fmi2Error;
    model_advance(self->v, communicationStepSize);
    model_outputs(self->v);
    self->outputs_stale = 0;
    self->time += communicationStepSize;
    return fmi2OK;
}

fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *FMUstate) {
    Instance *self = (Instance *)c;
    SavedState *saved = *FMUstate ? (SavedState *)*FMUstate : malloc(sizeof(SavedState));
    if (!saved) return fmi2Error;
    refresh_outputs(self);
    memcpy(saved->v, self->v, sizeof saved->v);
    saved->time = self->time;
    saved->mode = self->mode;
    *FMUstate = saved;
    return fmi2OK;
}

fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate FMUstate) {
    Instance *self = (Instance *)c;
    SavedState *saved = (SavedState *)FMUstate;
    memcpy(self->v, saved->v, sizeof self->v);
    self->time = saved->time;
    self->mode = saved->mode;
    self->outputs_stale = 0;
    return fmi2OK;
}

fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *FMUstate) {
    (void)c;
    free(*FMUstate);
    *FMUstate = NULL;
    return fmi2OK;
}

fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate FMUstate, size_t *size) {
    (void)c; (void)FMUstate;
    *size = sizeof(SavedState);
    return fmi2OK;
}

fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate FMUstate, fmi2Byte serializedState[],
                                 size_t size) {
    if (size != sizeof(SavedState)) return unsupported(c, "fmi2SerializeFMUstate of that size");
    memcpy(serializedState, FMUstate, sizeof(SavedState));
    return fmi2OK;
}

fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte serializedState[], size_t size,
                                   fmi2FMUstate *FMUstate) {
    if (size != sizeof(SavedState)) return unsupported(c, "fmi2DeSerializeFMUstate of that size");
    SavedState *saved = *FMUstate ? (SavedState *)*FMUstate : malloc(sizeof(SavedState));
    if (!saved) return fmi2Error;
    memcpy(saved, serializedState, sizeof(SavedState));
    *FMUstate = saved;
    return fmi2OK;
}

fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s, fmi2Status *value) {
    (void)s;
    *value = fmi2OK;
    (void)c;
    return fmi2OK;
}

fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *value) {
    if (s == fmi2LastSuccessfulTime) {
        *value = ((Instance *)c)->time;
        return fmi2OK;
    }
    return unsupported(c, "fmi2GetRealStatus of this kind");
}

/* ---- functions this FMU does not support: exported, refuse with a message ---- */
#define ACCESSOR(NAME, CONST, TYPE)                                                            \
    fmi2Status NAME(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, CONST TYPE value[]) { \
        (void)vr; (void)nvr; (void)value;                                                      \
        return unsupported(c, #NAME);                                                          \
    }
ACCESSOR(fmi2GetInteger, , fmi2Integer)
ACCESSOR(fmi2GetBoolean, , fmi2Boolean)
ACCESSOR(fmi2GetString, , fmi2String)
ACCESSOR(fmi2SetInteger, const, fmi2Integer)
ACCESSOR(fmi2SetBoolean, const, fmi2Boolean)
ACCESSOR(fmi2SetString, const, fmi2String)

fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference vUnknown_ref[],
                                        size_t nUnknown, const fmi2ValueReference vKnown_ref[],
                                        size_t nKnown, const fmi2Real dvKnown[], fmi2Real dvUnknown[]) {
    (void)vUnknown_ref; (void)nUnknown; (void)vKnown_ref; (void)nKnown; (void)dvKnown; (void)dvUnknown;
    return unsupported(c, "fmi2GetDirectionalDerivative");
}
fmi2Status fmi2EnterEventMode(fmi2Component c) { return unsupported(c, "fmi2EnterEventMode"); }
fmi2Status fmi2NewDiscreteStates(fmi2Component c, fmi2EventInfo *fmi2eventInfo) {
    (void)fmi2eventInfo;
    return unsupported(c, "fmi2NewDiscreteStates");
}
fmi2Status fmi2EnterContinuousTimeMode(fmi2Component c) { return unsupported(c, "fmi2EnterContinuousTimeMode"); }
fmi2Status fmi2CompletedIntegratorStep(fmi2Component c, fmi2Boolean noSetFMUStatePriorToCurrentPoint,
                                       fmi2Boolean *enterEventMode, fmi2Boolean *terminateSimulation) {
    (void)noSetFMUStatePriorToCurrentPoint; (void)enterEventMode; (void)terminateSimulation;
    return unsupported(c, "fmi2CompletedIntegratorStep");
}
fmi2Status fmi2SetTime(fmi2Component c, fmi2Real time) {
    (void)time;
    return unsupported(c, "fmi2SetTime");
}
#define STATE_ARRAY(NAME, CONST)                                                               \
    fmi2Status NAME(fmi2Component c, CONST fmi2Real x[], size_t n) {                           \
        (void)x; (void)n;                                                                      \
        return unsupported(c, #NAME);                                                          \
    }
STATE_ARRAY(fmi2SetContinuousStates, const)
STATE_ARRAY(fmi2GetDerivatives, )
STATE_ARRAY(fmi2GetEventIndicators, )
STATE_ARRAY(fmi2GetContinuousStates, )
STATE_ARRAY(fmi2GetNominalsOfContinuousStates, )
fmi2Status fmi2SetRealInputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                       const fmi2Integer order[], const fmi2Real value[]) {
    (void)vr; (void)nvr; (void)order; (void)value;
    return unsupported(c, "fmi2SetRealInputDerivatives");
}
fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                        const fmi2Integer order[], fmi2Real value[]) {
    (void)vr; (void)nvr; (void)order; (void)value;
    return unsupported(c, "fmi2GetRealOutputDerivatives");
}
fmi2Status fmi2CancelStep(fmi2Component c) { return unsupported(c, "fmi2CancelStep"); }
fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind s, fmi2Integer *value) {
    (void)s; (void)value;
    return unsupported(c, "fmi2GetIntegerStatus");
}
fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind s, fmi2Boolean *value) {
    (void)s; (void)value;
    return unsupported(c, "fmi2GetBooleanStatus");
}
fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind s, fmi2String *value) {
    (void)s; (void)value;
    return unsupported(c, "fmi2GetStringStatus");
}
