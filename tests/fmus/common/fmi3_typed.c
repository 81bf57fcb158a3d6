/* FMI 3.0 Co-Simulation wrapper of a typed test model (see typed_model.h):
 * variables of every FMI 3 type (not Clock; arrays of numbers and Booleans), event mode with early
 * return when the importer asks for it (hasEventMode), stop requests through
 * doStep's terminateSimulation. FMU state and every other function are
 * exported and refuse with a log message. */
#include <math.h>
#include <stdarg.h>
#include <stdbool.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi3Functions.h"
#include "typed_model.h"

typedef enum { MODE_INSTANTIATED, MODE_INITIALIZATION, MODE_EVENT, MODE_STEP, MODE_TERMINATED } Mode;

typedef struct {
    ModelData m;
    Mode mode;
    int event_mode_used;
    int early_return_allowed;
    fmi3InstanceEnvironment environment;
    fmi3LogMessageCallback log_message;
} Instance;

static void log_error(Instance *instance, const char *format, ...) {
    char message[1024];
    va_list args;
    va_start(args, format);
    vsnprintf(message, sizeof message, format, args);
    va_end(args);
    if (instance && instance->log_message)
        instance->log_message(instance->environment, fmi3Error, "logStatusError", message);
}

static fmi3Status unsupported(fmi3Instance instance, const char *function) {
    log_error((Instance *)instance, "%s is not supported by %s", function, MODEL_IDENTIFIER);
    return fmi3Error;
}

/* The variable with value reference vr if it has one of the types a, b (-1: none). */
static const VariableInfo *find(Instance *self, fmi3ValueReference vr, int a, int b,
                                const char *function, int setting) {
    for (size_t i = 0; i < N_VARIABLES; i++) {
        const VariableInfo *v = &VARIABLES[i];
        if (v->vr != vr) continue;
        if (v->type != a && v->type != b) {
            log_error(self, "%s: %s (value reference %u) has another type", function, v->name, vr);
            return NULL;
        }
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

static fmi3Status too_few(Instance *self, const char *function, size_t nValues) {
    log_error(self, "%s: nValues = %zu is too small", function, nValues);
    return fmi3Error;
}

#define NUMERIC_ACCESS(NAME, CTYPE, TYPE_A, TYPE_B)                                             \
    fmi3Status fmi3Get##NAME(fmi3Instance instance, const fmi3ValueReference valueReferences[], \
                             size_t nValueReferences, CTYPE values[], size_t nValues) {         \
        Instance *self = (Instance *)instance;                                                  \
        size_t n = 0;                                                                           \
        model_outputs(&self->m);                                                                \
        for (size_t i = 0; i < nValueReferences; i++) {                                         \
            const VariableInfo *v = find(self, valueReferences[i], TYPE_A, TYPE_B,              \
                                         "fmi3Get" #NAME, 0);                                   \
            if (!v) return fmi3Error;                                                           \
            if (n + v->count > nValues) return too_few(self, "fmi3Get" #NAME, nValues);         \
            memcpy(&values[n], VALUE(self, v), v->count * sizeof(CTYPE));                       \
            n += v->count;                                                                      \
        }                                                                                       \
        return fmi3OK;                                                                          \
    }                                                                                           \
    fmi3Status fmi3Set##NAME(fmi3Instance instance, const fmi3ValueReference valueReferences[], \
                             size_t nValueReferences, const CTYPE values[], size_t nValues) {   \
        Instance *self = (Instance *)instance;                                                  \
        size_t n = 0;                                                                           \
        for (size_t i = 0; i < nValueReferences; i++) {                                         \
            const VariableInfo *v = find(self, valueReferences[i], TYPE_A, TYPE_B,              \
                                         "fmi3Set" #NAME, 1);                                   \
            if (!v) return fmi3Error;                                                           \
            if (n + v->count > nValues) return too_few(self, "fmi3Set" #NAME, nValues);         \
            memcpy(VALUE(self, v), &values[n], v->count * sizeof(CTYPE));                       \
            n += v->count;                                                                      \
        }                                                                                       \
        return fmi3OK;                                                                          \
    }
NUMERIC_ACCESS(Float32, fmi3Float32, T_FLOAT32, -1)
NUMERIC_ACCESS(Float64, fmi3Float64, T_FLOAT64, -1)
NUMERIC_ACCESS(Int8, fmi3Int8, T_INT8, -1)
NUMERIC_ACCESS(UInt8, fmi3UInt8, T_UINT8, -1)
NUMERIC_ACCESS(Int16, fmi3Int16, T_INT16, -1)
NUMERIC_ACCESS(UInt16, fmi3UInt16, T_UINT16, -1)
NUMERIC_ACCESS(Int32, fmi3Int32, T_INT32, -1)
NUMERIC_ACCESS(UInt32, fmi3UInt32, T_UINT32, -1)
NUMERIC_ACCESS(Int64, fmi3Int64, T_INT64, T_ENUMERATION)
NUMERIC_ACCESS(UInt64, fmi3UInt64, T_UINT64, -1)
NUMERIC_ACCESS(Boolean, fmi3Boolean, T_BOOLEAN, -1)

fmi3Status fmi3GetString(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                         size_t nValueReferences, fmi3String values[], size_t nValues) {
    Instance *self = (Instance *)instance;
    if (nValues < nValueReferences) return unsupported(instance, "arrays in fmi3GetString");
    model_outputs(&self->m);
    for (size_t i = 0; i < nValueReferences; i++) {
        const VariableInfo *v = find(self, valueReferences[i], T_STRING, -1, "fmi3GetString", 0);
        if (!v) return fmi3Error;
        values[i] = VALUE(self, v);
    }
    return fmi3OK;
}

fmi3Status fmi3SetString(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                         size_t nValueReferences, const fmi3String values[], size_t nValues) {
    Instance *self = (Instance *)instance;
    if (nValues < nValueReferences) return unsupported(instance, "arrays in fmi3SetString");
    for (size_t i = 0; i < nValueReferences; i++) {
        const VariableInfo *v = find(self, valueReferences[i], T_STRING, -1, "fmi3SetString", 1);
        if (!v) return fmi3Error;
        const char *text = values[i] ? values[i] : "";
        if (strlen(text) >= STRING_CAPACITY) {
            log_error(self, "%s: at most %d bytes", v->name, STRING_CAPACITY - 1);
            return fmi3Error;
        }
        strcpy(VALUE(self, v), text);
    }
    return fmi3OK;
}

fmi3Status fmi3GetBinary(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                         size_t nValueReferences, size_t valueSizes[], fmi3Binary values[],
                         size_t nValues) {
    Instance *self = (Instance *)instance;
    if (nValues < nValueReferences) return unsupported(instance, "arrays in fmi3GetBinary");
    model_outputs(&self->m);
    for (size_t i = 0; i < nValueReferences; i++) {
        const VariableInfo *v = find(self, valueReferences[i], T_BINARY, -1, "fmi3GetBinary", 0);
        if (!v) return fmi3Error;
        values[i] = (fmi3Binary)VALUE(self, v);
        memcpy(&valueSizes[i], (char *)&self->m + v->size_offset, sizeof(size_t));
    }
    return fmi3OK;
}

fmi3Status fmi3SetBinary(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                         size_t nValueReferences, const size_t valueSizes[],
                         const fmi3Binary values[], size_t nValues) {
    Instance *self = (Instance *)instance;
    if (nValues < nValueReferences) return unsupported(instance, "arrays in fmi3SetBinary");
    for (size_t i = 0; i < nValueReferences; i++) {
        const VariableInfo *v = find(self, valueReferences[i], T_BINARY, -1, "fmi3SetBinary", 1);
        if (!v) return fmi3Error;
        if (valueSizes[i] > BINARY_CAPACITY) {
            log_error(self, "%s: at most %d bytes", v->name, BINARY_CAPACITY);
            return fmi3Error;
        }
        if (valueSizes[i]) memcpy(VALUE(self, v), values[i], valueSizes[i]);
        memcpy((char *)&self->m + v->size_offset, &valueSizes[i], sizeof(size_t));
    }
    return fmi3OK;
}

const char *fmi3GetVersion(void) { return fmi3Version; }

fmi3Status fmi3SetDebugLogging(fmi3Instance instance, fmi3Boolean loggingOn, size_t nCategories,
                               const fmi3String categories[]) {
    (void)instance; (void)loggingOn; (void)nCategories; (void)categories;
    return fmi3OK;
}

fmi3Instance fmi3InstantiateModelExchange(fmi3String instanceName, fmi3String instantiationToken,
                                          fmi3String resourcePath, fmi3Boolean visible,
                                          fmi3Boolean loggingOn,
                                          fmi3InstanceEnvironment instanceEnvironment,
                                          fmi3LogMessageCallback logMessage) {
    (void)instanceName; (void)instantiationToken; (void)resourcePath; (void)visible;
    (void)loggingOn;
    if (logMessage)
        logMessage(instanceEnvironment, fmi3Error, "logStatusError",
                   MODEL_IDENTIFIER " supports Co-Simulation only");
    return NULL;
}

fmi3Instance fmi3InstantiateCoSimulation(
    fmi3String instanceName, fmi3String instantiationToken, fmi3String resourcePath,
    fmi3Boolean visible, fmi3Boolean loggingOn, fmi3Boolean eventModeUsed,
    fmi3Boolean earlyReturnAllowed, const fmi3ValueReference requiredIntermediateVariables[],
    size_t nRequiredIntermediateVariables, fmi3InstanceEnvironment instanceEnvironment,
    fmi3LogMessageCallback logMessage, fmi3IntermediateUpdateCallback intermediateUpdate) {
    (void)instanceName; (void)resourcePath; (void)visible; (void)loggingOn;
    (void)requiredIntermediateVariables; (void)nRequiredIntermediateVariables;
    (void)intermediateUpdate;
    if (!instantiationToken || strcmp(instantiationToken, INSTANTIATION_TOKEN) != 0) {
        if (logMessage)
            logMessage(instanceEnvironment, fmi3Error, "logStatusError",
                       "instantiationToken does not match this binary of " MODEL_IDENTIFIER);
        return NULL;
    }
    Instance *self = calloc(1, sizeof(Instance));
    if (!self) return NULL;
    set_start_values(&self->m);
    self->mode = MODE_INSTANTIATED;
    self->event_mode_used = eventModeUsed && HAS_EVENT_MODE;
    self->early_return_allowed = earlyReturnAllowed;
    self->environment = instanceEnvironment;
    self->log_message = logMessage;
    return self;
}

fmi3Instance fmi3InstantiateScheduledExecution(
    fmi3String instanceName, fmi3String instantiationToken, fmi3String resourcePath,
    fmi3Boolean visible, fmi3Boolean loggingOn, fmi3InstanceEnvironment instanceEnvironment,
    fmi3LogMessageCallback logMessage, fmi3ClockUpdateCallback clockUpdate,
    fmi3LockPreemptionCallback lockPreemption, fmi3UnlockPreemptionCallback unlockPreemption) {
    (void)instanceName; (void)instantiationToken; (void)resourcePath; (void)visible;
    (void)loggingOn; (void)clockUpdate; (void)lockPreemption; (void)unlockPreemption;
    if (logMessage)
        logMessage(instanceEnvironment, fmi3Error, "logStatusError",
                   MODEL_IDENTIFIER " supports Co-Simulation only");
    return NULL;
}

void fmi3FreeInstance(fmi3Instance instance) { free(instance); }

fmi3Status fmi3EnterInitializationMode(fmi3Instance instance, fmi3Boolean toleranceDefined,
                                       fmi3Float64 tolerance, fmi3Float64 startTime,
                                       fmi3Boolean stopTimeDefined, fmi3Float64 stopTime) {
    (void)toleranceDefined; (void)tolerance; (void)stopTimeDefined; (void)stopTime;
    Instance *self = (Instance *)instance;
    self->m.time = startTime;
    self->mode = MODE_INITIALIZATION;
    return fmi3OK;
}

fmi3Status fmi3ExitInitializationMode(fmi3Instance instance) {
    Instance *self = (Instance *)instance;
    char message[512];
    if (model_check(&self->m, message, sizeof message)) {
        log_error(self, "%s", message);
        return fmi3Error;
    }
    self->mode = self->event_mode_used ? MODE_EVENT : MODE_STEP;
    return fmi3OK;
}

fmi3Status fmi3EnterEventMode(fmi3Instance instance) {
    Instance *self = (Instance *)instance;
    if (!self->event_mode_used) return unsupported(instance, "fmi3EnterEventMode without event mode");
    self->mode = MODE_EVENT;
    return fmi3OK;
}

fmi3Status fmi3UpdateDiscreteStates(fmi3Instance instance, fmi3Boolean *discreteStatesNeedUpdate,
                                    fmi3Boolean *terminateSimulation,
                                    fmi3Boolean *nominalsOfContinuousStatesChanged,
                                    fmi3Boolean *valuesOfContinuousStatesChanged,
                                    fmi3Boolean *nextEventTimeDefined, fmi3Float64 *nextEventTime) {
    Instance *self = (Instance *)instance;
    if (self->mode != MODE_EVENT) {
        log_error(self, "fmi3UpdateDiscreteStates called outside event mode");
        return fmi3Error;
    }
    *terminateSimulation = model_event_update(&self->m) ? fmi3True : fmi3False;
    *discreteStatesNeedUpdate = fmi3False;
    *nominalsOfContinuousStatesChanged = fmi3False;
    *valuesOfContinuousStatesChanged = fmi3False;
    *nextEventTimeDefined = fmi3False;
    *nextEventTime = 0.0;
    return fmi3OK;
}

fmi3Status fmi3EnterStepMode(fmi3Instance instance) {
    Instance *self = (Instance *)instance;
    if (self->mode != MODE_EVENT) {
        log_error(self, "fmi3EnterStepMode called outside event mode");
        return fmi3Error;
    }
    self->mode = MODE_STEP;
    return fmi3OK;
}

fmi3Status fmi3Terminate(fmi3Instance instance) {
    ((Instance *)instance)->mode = MODE_TERMINATED;
    return fmi3OK;
}

fmi3Status fmi3Reset(fmi3Instance instance) {
    Instance *self = (Instance *)instance;
    set_start_values(&self->m);
    self->m.time = 0.0;
    self->mode = MODE_INSTANTIATED;
    return fmi3OK;
}

fmi3Status fmi3DoStep(fmi3Instance instance, fmi3Float64 currentCommunicationPoint,
                      fmi3Float64 communicationStepSize, fmi3Boolean noSetFMUStatePriorToCurrentPoint,
                      fmi3Boolean *eventHandlingNeeded, fmi3Boolean *terminateSimulation,
                      fmi3Boolean *earlyReturn, fmi3Float64 *lastSuccessfulTime) {
    (void)noSetFMUStatePriorToCurrentPoint;
    Instance *self = (Instance *)instance;
    *eventHandlingNeeded = fmi3False;
    *terminateSimulation = fmi3False;
    *earlyReturn = fmi3False;
    *lastSuccessfulTime = self->m.time;
    if (self->mode != MODE_STEP) {
        log_error(self, "fmi3DoStep called outside step mode");
        return fmi3Error;
    }
    if (!(communicationStepSize > 0.0) || !isfinite(communicationStepSize)) {
        log_error(self, "communicationStepSize = %g: must be finite and > 0 s", communicationStepSize);
        return fmi3Error;
    }
    double end = currentCommunicationPoint + communicationStepSize;
    StepResult result = model_advance(&self->m, end,
                                      self->event_mode_used && self->early_return_allowed);
    *lastSuccessfulTime = self->m.time;
    if (result == STEP_EVENT) {
        *eventHandlingNeeded = fmi3True;
        *earlyReturn = self->m.time < end ? fmi3True : fmi3False;
    } else if (result == STEP_TERMINATE) {
        *terminateSimulation = fmi3True;
        *earlyReturn = (self->early_return_allowed && self->m.time < end) ? fmi3True : fmi3False;
    }
    return fmi3OK;
}
/* ---- functions a test model does not support: exported, refuse with a message ---- */
fmi3Status fmi3EvaluateDiscreteStates(fmi3Instance instance) { return unsupported(instance, "fmi3EvaluateDiscreteStates"); }
#define STATE_FUNCTION(NAME, ARGS, UNUSED) fmi3Status NAME ARGS { UNUSED; return unsupported(instance, #NAME); }
STATE_FUNCTION(fmi3GetFMUState, (fmi3Instance instance, fmi3FMUState *FMUState), (void)FMUState)
STATE_FUNCTION(fmi3SetFMUState, (fmi3Instance instance, fmi3FMUState FMUState), (void)FMUState)
STATE_FUNCTION(fmi3FreeFMUState, (fmi3Instance instance, fmi3FMUState *FMUState), (void)FMUState)
STATE_FUNCTION(fmi3SerializedFMUStateSize, (fmi3Instance instance, fmi3FMUState FMUState, size_t *size), (void)FMUState; (void)size)
STATE_FUNCTION(fmi3SerializeFMUState, (fmi3Instance instance, fmi3FMUState FMUState, fmi3Byte serializedState[], size_t size), (void)FMUState; (void)serializedState; (void)size)
STATE_FUNCTION(fmi3DeserializeFMUState, (fmi3Instance instance, const fmi3Byte serializedState[], size_t size, fmi3FMUState *FMUState), (void)FMUState; (void)serializedState; (void)size)
fmi3Status fmi3GetClock(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                        size_t nValueReferences, fmi3Clock values[]) {
    (void)valueReferences; (void)nValueReferences; (void)values;
    return unsupported(instance, "fmi3GetClock");
}
fmi3Status fmi3SetClock(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                        size_t nValueReferences, const fmi3Clock values[]) {
    (void)valueReferences; (void)nValueReferences; (void)values;
    return unsupported(instance, "fmi3SetClock");
}
fmi3Status fmi3GetNumberOfVariableDependencies(fmi3Instance instance, fmi3ValueReference valueReference,
                                               size_t *nDependencies) {
    (void)valueReference; (void)nDependencies;
    return unsupported(instance, "fmi3GetNumberOfVariableDependencies");
}
fmi3Status fmi3GetVariableDependencies(fmi3Instance instance, fmi3ValueReference dependent,
                                       size_t elementIndicesOfDependent[],
                                       fmi3ValueReference independents[],
                                       size_t elementIndicesOfIndependents[],
                                       fmi3DependencyKind dependencyKinds[], size_t nDependencies) {
    (void)dependent; (void)elementIndicesOfDependent; (void)independents;
    (void)elementIndicesOfIndependents; (void)dependencyKinds; (void)nDependencies;
    return unsupported(instance, "fmi3GetVariableDependencies");
}
#define DERIVATIVE(NAME)                                                                        \
    fmi3Status NAME(fmi3Instance instance, const fmi3ValueReference unknowns[], size_t nUnknowns, \
                    const fmi3ValueReference knowns[], size_t nKnowns, const fmi3Float64 seed[], \
                    size_t nSeed, fmi3Float64 sensitivity[], size_t nSensitivity) {              \
        (void)unknowns; (void)nUnknowns; (void)knowns; (void)nKnowns; (void)seed; (void)nSeed;  \
        (void)sensitivity; (void)nSensitivity;                                                  \
        return unsupported(instance, #NAME);                                                    \
    }
DERIVATIVE(fmi3GetDirectionalDerivative)
DERIVATIVE(fmi3GetAdjointDerivative)
fmi3Status fmi3EnterConfigurationMode(fmi3Instance instance) { return unsupported(instance, "fmi3EnterConfigurationMode"); }
fmi3Status fmi3ExitConfigurationMode(fmi3Instance instance) { return unsupported(instance, "fmi3ExitConfigurationMode"); }
fmi3Status fmi3GetIntervalDecimal(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                                  size_t nValueReferences, fmi3Float64 intervals[],
                                  fmi3IntervalQualifier qualifiers[]) {
    (void)valueReferences; (void)nValueReferences; (void)intervals; (void)qualifiers;
    return unsupported(instance, "fmi3GetIntervalDecimal");
}
fmi3Status fmi3GetIntervalFraction(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                                   size_t nValueReferences, fmi3UInt64 counters[],
                                   fmi3UInt64 resolutions[], fmi3IntervalQualifier qualifiers[]) {
    (void)valueReferences; (void)nValueReferences; (void)counters; (void)resolutions; (void)qualifiers;
    return unsupported(instance, "fmi3GetIntervalFraction");
}
fmi3Status fmi3GetShiftDecimal(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                               size_t nValueReferences, fmi3Float64 shifts[]) {
    (void)valueReferences; (void)nValueReferences; (void)shifts;
    return unsupported(instance, "fmi3GetShiftDecimal");
}
fmi3Status fmi3GetShiftFraction(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                                size_t nValueReferences, fmi3UInt64 counters[], fmi3UInt64 resolutions[]) {
    (void)valueReferences; (void)nValueReferences; (void)counters; (void)resolutions;
    return unsupported(instance, "fmi3GetShiftFraction");
}
fmi3Status fmi3SetIntervalDecimal(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                                  size_t nValueReferences, const fmi3Float64 intervals[]) {
    (void)valueReferences; (void)nValueReferences; (void)intervals;
    return unsupported(instance, "fmi3SetIntervalDecimal");
}
fmi3Status fmi3SetIntervalFraction(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                                   size_t nValueReferences, const fmi3UInt64 counters[],
                                   const fmi3UInt64 resolutions[]) {
    (void)valueReferences; (void)nValueReferences; (void)counters; (void)resolutions;
    return unsupported(instance, "fmi3SetIntervalFraction");
}
fmi3Status fmi3SetShiftDecimal(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                               size_t nValueReferences, const fmi3Float64 shifts[]) {
    (void)valueReferences; (void)nValueReferences; (void)shifts;
    return unsupported(instance, "fmi3SetShiftDecimal");
}
fmi3Status fmi3SetShiftFraction(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                                size_t nValueReferences, const fmi3UInt64 counters[],
                                const fmi3UInt64 resolutions[]) {
    (void)valueReferences; (void)nValueReferences; (void)counters; (void)resolutions;
    return unsupported(instance, "fmi3SetShiftFraction");
}
fmi3Status fmi3EnterContinuousTimeMode(fmi3Instance instance) { return unsupported(instance, "fmi3EnterContinuousTimeMode"); }
fmi3Status fmi3CompletedIntegratorStep(fmi3Instance instance, fmi3Boolean noSetFMUStatePriorToCurrentPoint,
                                       fmi3Boolean *enterEventMode, fmi3Boolean *terminateSimulation) {
    (void)noSetFMUStatePriorToCurrentPoint; (void)enterEventMode; (void)terminateSimulation;
    return unsupported(instance, "fmi3CompletedIntegratorStep");
}
fmi3Status fmi3SetTime(fmi3Instance instance, fmi3Float64 time) {
    (void)time;
    return unsupported(instance, "fmi3SetTime");
}
#define STATE_ARRAY(NAME, CONST)                                                                \
    fmi3Status NAME(fmi3Instance instance, CONST fmi3Float64 values[], size_t n) {              \
        (void)values; (void)n;                                                                  \
        return unsupported(instance, #NAME);                                                    \
    }
STATE_ARRAY(fmi3SetContinuousStates, const)
STATE_ARRAY(fmi3GetContinuousStateDerivatives, )
STATE_ARRAY(fmi3GetEventIndicators, )
STATE_ARRAY(fmi3GetContinuousStates, )
STATE_ARRAY(fmi3GetNominalsOfContinuousStates, )
fmi3Status fmi3GetNumberOfEventIndicators(fmi3Instance instance, size_t *nEventIndicators) {
    (void)nEventIndicators;
    return unsupported(instance, "fmi3GetNumberOfEventIndicators");
}
fmi3Status fmi3GetNumberOfContinuousStates(fmi3Instance instance, size_t *nContinuousStates) {
    (void)nContinuousStates;
    return unsupported(instance, "fmi3GetNumberOfContinuousStates");
}
fmi3Status fmi3GetOutputDerivatives(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                                    size_t nValueReferences, const fmi3Int32 orders[],
                                    fmi3Float64 values[], size_t nValues) {
    (void)valueReferences; (void)nValueReferences; (void)orders; (void)values; (void)nValues;
    return unsupported(instance, "fmi3GetOutputDerivatives");
}
fmi3Status fmi3ActivateModelPartition(fmi3Instance instance, fmi3ValueReference clockReference,
                                      fmi3Float64 activationTime) {
    (void)clockReference; (void)activationTime;
    return unsupported(instance, "fmi3ActivateModelPartition");
}

