/* FMI 2.0 Co-Simulation wrapper of a typed test model (see typed_model.h):
 * Real, Integer, Boolean, String and Enumeration variables (array elements
 * name[i] are scalars of their own); events
 * are handled inside doStep (FMI 2 Co-Simulation has no event mode); a stop
 * request is fmi2Discard with fmi2GetBooleanStatus(fmi2Terminated) true and
 * fmi2GetRealStatus(fmi2LastSuccessfulTime) the model's time. FMU state and
 * every other function are exported and refuse with a log message. */
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi2Functions.h"
#include "typed_model.h"

typedef enum { MODE_INSTANTIATED, MODE_INITIALIZATION, MODE_STEP, MODE_TERMINATED } Mode;

typedef struct {
    ModelData m;
    Mode mode;
    int terminated;
    char *name;
    fmi2CallbackFunctions callbacks;
} Instance;

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

static const VariableInfo *find(Instance *self, fmi2ValueReference vr, int a, int b,
                                const char *function, int setting) {
    for (size_t i = 0; i < N_VARIABLES; i++) {
        const VariableInfo *v = &VARIABLES[i];
        if (v->vr != vr) continue;
        if (v->type != a && v->type != b) continue;  /* FMI 2: one namespace per type */
        if (setting && (v->causality == C_OUTPUT || v->causality == C_INDEPENDENT ||
                        (v->causality == C_PARAMETER && self->mode != MODE_INSTANTIATED &&
                         self->mode != MODE_INITIALIZATION))) {
            log_error(self, "%s: %s cannot be set now", function, v->name);
            return NULL;
        }
        return v;
    }
    log_error(self, "%s: unknown value reference %u", function, vr);
    return NULL;
}

#define VALUE(self, v) ((char *)&(self)->m + (v)->offset)

#define NUMERIC_ACCESS(NAME, CTYPE, TYPE_A, TYPE_B)                                             \
    fmi2Status fmi2Get##NAME(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,        \
                             CTYPE value[]) {                                                   \
        Instance *self = (Instance *)c;                                                         \
        model_outputs(&self->m);                                                                \
        for (size_t i = 0; i < nvr; i++) {                                                      \
            const VariableInfo *v = find(self, vr[i], TYPE_A, TYPE_B, "fmi2Get" #NAME, 0);      \
            if (!v) return fmi2Error;                                                           \
            memcpy(&value[i], VALUE(self, v), sizeof(CTYPE));                                   \
        }                                                                                       \
        return fmi2OK;                                                                          \
    }                                                                                           \
    fmi2Status fmi2Set##NAME(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,        \
                             const CTYPE value[]) {                                             \
        Instance *self = (Instance *)c;                                                         \
        for (size_t i = 0; i < nvr; i++) {                                                      \
            const VariableInfo *v = find(self, vr[i], TYPE_A, TYPE_B, "fmi2Set" #NAME, 1);      \
            if (!v) return fmi2Error;                                                           \
            memcpy(VALUE(self, v), &value[i], sizeof(CTYPE));                                   \
        }                                                                                       \
        return fmi2OK;                                                                          \
    }
NUMERIC_ACCESS(Real, fmi2Real, T_FLOAT64, -1)
NUMERIC_ACCESS(Integer, fmi2Integer, T_INT32, T_ENUMERATION)
NUMERIC_ACCESS(Boolean, fmi2Boolean, T_BOOLEAN, -1)

fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                         fmi2String value[]) {
    Instance *self = (Instance *)c;
    model_outputs(&self->m);
    for (size_t i = 0; i < nvr; i++) {
        const VariableInfo *v = find(self, vr[i], T_STRING, -1, "fmi2GetString", 0);
        if (!v) return fmi2Error;
        value[i] = VALUE(self, v);
    }
    return fmi2OK;
}

fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                         const fmi2String value[]) {
    Instance *self = (Instance *)c;
    for (size_t i = 0; i < nvr; i++) {
        const VariableInfo *v = find(self, vr[i], T_STRING, -1, "fmi2SetString", 1);
        if (!v) return fmi2Error;
        const char *text = value[i] ? value[i] : "";
        if (strlen(text) >= STRING_CAPACITY) {
            log_error(self, "%s: at most %d bytes", v->name, STRING_CAPACITY - 1);
            return fmi2Error;
        }
        strcpy(VALUE(self, v), text);
    }
    return fmi2OK;
}

const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }
const char *fmi2GetVersion(void) { return fmi2Version; }

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean loggingOn, size_t nCategories,
                               const fmi2String categories[]) {
    (void)c; (void)loggingOn; (void)nCategories; (void)categories;
    return fmi2OK;
}

fmi2Component fmi2Instantiate(fmi2String instanceName, fmi2Type fmuType, fmi2String fmuGUID,
                              fmi2String fmuResourceLocation,
                              const fmi2CallbackFunctions *functions, fmi2Boolean visible,
                              fmi2Boolean loggingOn) {
    (void)fmuResourceLocation; (void)visible; (void)loggingOn;
    if (fmuType != fmi2CoSimulation || !fmuGUID || strcmp(fmuGUID, INSTANTIATION_TOKEN) != 0) {
        if (functions && functions->logger)
            functions->logger(functions->componentEnvironment, instanceName, fmi2Error,
                              "logStatusError", "%s",
                              "not a Co-Simulation instance of this binary of " MODEL_IDENTIFIER);
        return NULL;
    }
    Instance *self = calloc(1, sizeof(Instance));
    if (!self) return NULL;
    const char *name = instanceName ? instanceName : MODEL_IDENTIFIER;
    self->name = malloc(strlen(name) + 1);
    if (self->name) strcpy(self->name, name);
    set_start_values(&self->m);
    self->mode = MODE_INSTANTIATED;
    if (functions) self->callbacks = *functions;
    return self;
}

void fmi2FreeInstance(fmi2Component c) {
    if (!c) return;
    free(((Instance *)c)->name);
    free(c);
}

fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean toleranceDefined, fmi2Real tolerance,
                               fmi2Real startTime, fmi2Boolean stopTimeDefined, fmi2Real stopTime) {
    (void)toleranceDefined; (void)tolerance; (void)stopTimeDefined; (void)stopTime;
    ((Instance *)c)->m.time = startTime;
    return fmi2OK;
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c) {
    ((Instance *)c)->mode = MODE_INITIALIZATION;
    return fmi2OK;
}

fmi2Status fmi2ExitInitializationMode(fmi2Component c) {
    Instance *self = (Instance *)c;
    char message[512];
    if (model_check(&self->m, message, sizeof message)) {
        log_error(self, "%s", message);
        return fmi2Error;
    }
    self->mode = MODE_STEP;
    return fmi2OK;
}

fmi2Status fmi2Terminate(fmi2Component c) {
    ((Instance *)c)->mode = MODE_TERMINATED;
    return fmi2OK;
}

fmi2Status fmi2Reset(fmi2Component c) {
    Instance *self = (Instance *)c;
    set_start_values(&self->m);
    self->m.time = 0.0;
    self->terminated = 0;
    self->mode = MODE_INSTANTIATED;
    return fmi2OK;
}

fmi2Status fmi2DoStep(fmi2Component c, fmi2Real currentCommunicationPoint,
                      fmi2Real communicationStepSize, fmi2Boolean noSetFMUStatePriorToCurrentPoint) {
    (void)noSetFMUStatePriorToCurrentPoint;
    Instance *self = (Instance *)c;
    if (self->mode != MODE_STEP) {
        log_error(self, "fmi2DoStep called outside step mode");
        return fmi2Error;
    }
    if (self->terminated) return fmi2Discard;
    if (!(communicationStepSize > 0.0) || !isfinite(communicationStepSize)) {
        log_error(self, "communicationStepSize = %g: must be finite and > 0 s", communicationStepSize);
        return fmi2Error;
    }
    if (model_advance(&self->m, currentCommunicationPoint + communicationStepSize, 0) ==
        STEP_TERMINATE) {
        self->terminated = 1;
        return fmi2Discard;
    }
    return fmi2OK;
}

fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s, fmi2Status *value) {
    (void)s;
    *value = ((Instance *)c)->terminated ? fmi2Discard : fmi2OK;
    return fmi2OK;
}

fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *value) {
    if (s != fmi2LastSuccessfulTime) return unsupported(c, "fmi2GetRealStatus of this kind");
    *value = ((Instance *)c)->m.time;
    return fmi2OK;
}

fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind s, fmi2Boolean *value) {
    if (s != fmi2Terminated) return unsupported(c, "fmi2GetBooleanStatus of this kind");
    *value = ((Instance *)c)->terminated ? fmi2True : fmi2False;
    return fmi2OK;
}

/* ---- functions a test model does not support: exported, refuse with a message ---- */
fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *FMUstate) {
    (void)FMUstate;
    return unsupported(c, "fmi2GetFMUstate");
}
fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate FMUstate) {
    (void)FMUstate;
    return unsupported(c, "fmi2SetFMUstate");
}
fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *FMUstate) {
    (void)FMUstate;
    return unsupported(c, "fmi2FreeFMUstate");
}
fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate FMUstate, size_t *size) {
    (void)FMUstate; (void)size;
    return unsupported(c, "fmi2SerializedFMUstateSize");
}
fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate FMUstate, fmi2Byte serializedState[],
                                 size_t size) {
    (void)FMUstate; (void)serializedState; (void)size;
    return unsupported(c, "fmi2SerializeFMUstate");
}
fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte serializedState[], size_t size,
                                   fmi2FMUstate *FMUstate) {
    (void)FMUstate; (void)serializedState; (void)size;
    return unsupported(c, "fmi2DeSerializeFMUstate");
}
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
fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind s, fmi2String *value) {
    (void)s; (void)value;
    return unsupported(c, "fmi2GetStringStatus");
}

