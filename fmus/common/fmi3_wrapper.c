/* FMI 3.0 Co-Simulation wrapper around one model source (see model.h).
 * Supports Float64 variables (scalars and arrays), get/set/serialize FMU
 * state; every other FMI 3.0 function is exported and returns fmi3Error with
 * a log message, so the FMU loads in any FMI 3.0 importer. */
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi3Functions.h"
#include "model.h"

typedef enum { MODE_INSTANTIATED, MODE_INITIALIZATION, MODE_STEP, MODE_TERMINATED } Mode;

typedef struct {
    double v[N_VALUES];
    double time;
    Mode mode;
    int outputs_stale;
    int logging_on;
    char *name;
    fmi3InstanceEnvironment environment;
    fmi3LogMessageCallback log_message;
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
    if (instance && instance->log_message)
        instance->log_message(instance->environment, fmi3Error, "logStatusError", message);
}

static fmi3Status unsupported(fmi3Instance instance, const char *function) {
    log_error((Instance *)instance, "%s is not supported by %s", function, MODEL_IDENTIFIER);
    return fmi3Error;
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

const char *fmi3GetVersion(void) { return fmi3Version; }

fmi3Status fmi3SetDebugLogging(fmi3Instance instance, fmi3Boolean loggingOn, size_t nCategories,
                               const fmi3String categories[]) {
    (void)nCategories; (void)categories;
    ((Instance *)instance)->logging_on = loggingOn;
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
    (void)resourcePath; (void)visible; (void)eventModeUsed; (void)earlyReturnAllowed;
    (void)requiredIntermediateVariables; (void)nRequiredIntermediateVariables;
    (void)intermediateUpdate;
    if (!instantiationToken || strcmp(instantiationToken, INSTANTIATION_TOKEN) != 0) {
        if (logMessage)
            logMessage(instanceEnvironment, fmi3Error, "logStatusError",
                       "instantiationToken does not match this binary of " MODEL_IDENTIFIER);
        return NULL;
    }
    Instance *instance = calloc(1, sizeof(Instance));
    if (!instance) return NULL;
    const char *name = instanceName ? instanceName : MODEL_IDENTIFIER;
    instance->name = malloc(strlen(name) + 1);
    if (instance->name) strcpy(instance->name, name);
    memcpy(instance->v, START_VALUES, sizeof instance->v);
    instance->mode = MODE_INSTANTIATED;
    instance->outputs_stale = 1;
    instance->logging_on = loggingOn;
    instance->environment = instanceEnvironment;
    instance->log_message = logMessage;
    return instance;
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

void fmi3FreeInstance(fmi3Instance instance) {
    if (!instance) return;
    free(((Instance *)instance)->name);
    free(instance);
}

fmi3Status fmi3EnterInitializationMode(fmi3Instance instance, fmi3Boolean toleranceDefined,
                                       fmi3Float64 tolerance, fmi3Float64 startTime,
                                       fmi3Boolean stopTimeDefined, fmi3Float64 stopTime) {
    (void)toleranceDefined; (void)tolerance; (void)stopTimeDefined; (void)stopTime;
    Instance *self = (Instance *)instance;
    self->time = startTime;
    self->mode = MODE_INITIALIZATION;
    return fmi3OK;
}

fmi3Status fmi3ExitInitializationMode(fmi3Instance instance) {
    Instance *self = (Instance *)instance;
    char message[512];
    if (check_values(self, CAUSALITY_PARAMETER)) return fmi3Error;
    if (model_check_parameters(self->v, message, sizeof message)) {
        log_error(self, "%s", message);
        return fmi3Error;
    }
    if (check_values(self, CAUSALITY_INPUT)) return fmi3Error;
    model_initialize(self->v);
    model_outputs(self->v);
    self->outputs_stale = 0;
    self->mode = MODE_STEP;
    return fmi3OK;
}

fmi3Status fmi3EnterEventMode(fmi3Instance instance) { return unsupported(instance, "fmi3EnterEventMode"); }

fmi3Status fmi3Terminate(fmi3Instance instance) {
    ((Instance *)instance)->mode = MODE_TERMINATED;
    return fmi3OK;
}

fmi3Status fmi3Reset(fmi3Instance instance) {
    Instance *self = (Instance *)instance;
    memcpy(self->v, START_VALUES, sizeof self->v);
    self->time = 0.0;
    self->mode = MODE_INSTANTIATED;
    self->outputs_stale = 1;
    return fmi3OK;
}

fmi3Status fmi3GetFloat64(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                          size_t nValueReferences, fmi3Float64 values[], size_t nValues) {
    Instance *self = (Instance *)instance;
    size_t n = 0;
    if (self->mode == MODE_STEP || self->mode == MODE_INITIALIZATION) refresh_outputs(self);
    for (size_t i = 0; i < nValueReferences; i++) {
        fmi3ValueReference vr = valueReferences[i];
        if (vr == 0) {
            if (n + 1 > nValues) goto too_few;
            values[n++] = self->time;
            continue;
        }
        if (vr > N_VARIABLES) {
            log_error(self, "fmi3GetFloat64: unknown value reference %u", vr);
            return fmi3Error;
        }
        int size = VARIABLE_SIZE[vr];
        if (n + size > nValues) goto too_few;
        memcpy(values + n, self->v + VARIABLE_OFFSET[vr], size * sizeof(double));
        n += size;
    }
    return fmi3OK;
too_few:
    log_error(self, "fmi3GetFloat64: nValues = %zu is too small", nValues);
    return fmi3Error;
}

fmi3Status fmi3SetFloat64(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                          size_t nValueReferences, const fmi3Float64 values[], size_t nValues) {
    Instance *self = (Instance *)instance;
    size_t n = 0;
    for (size_t i = 0; i < nValueReferences; i++) {
        fmi3ValueReference vr = valueReferences[i];
        if (vr == 0 || vr > N_VARIABLES) {
            log_error(self, "fmi3SetFloat64: value reference %u is not settable", vr);
            return fmi3Error;
        }
        int causality = VARIABLE_CAUSALITY[vr];
        if (causality == CAUSALITY_OUTPUT ||
            (causality == CAUSALITY_PARAMETER && self->mode == MODE_STEP)) {
            log_error(self, "fmi3SetFloat64: %s (%s) cannot be set now", VARIABLE_NAME[vr],
                      causality == CAUSALITY_OUTPUT ? "an output" : "a fixed parameter");
            return fmi3Error;
        }
        int size = VARIABLE_SIZE[vr];
        if (n + size > nValues) {
            log_error(self, "fmi3SetFloat64: nValues = %zu is too small", nValues);
            return fmi3Error;
        }
        memcpy(self->v + VARIABLE_OFFSET[vr], values + n, size * sizeof(double));
        n += size;
    }
    self->outputs_stale = 1;
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
    *lastSuccessfulTime = self->time;
    if (self->mode != MODE_STEP) {
        log_error(self, "fmi3DoStep called outside step mode");
        return fmi3Error;
    }
    if (!(communicationStepSize > 0.0) || !isfinite(communicationStepSize)) {
        log_error(self, "communicationStepSize = %g: must be finite and > 0 s", communicationStepSize);
        return fmi3Error;
    }
    if (check_values(self, CAUSALITY_INPUT)) return fmi3Error;
    (void)currentCommunicationPoint;
    model_advance(self->v, communicationStepSize);
    model_outputs(self->v);
    self->outputs_stale = 0;
    self->time += communicationStepSize;
    *lastSuccessfulTime = self->time;
    return fmi3OK;
}

fmi3Status fmi3GetFMUState(fmi3Instance instance, fmi3FMUState *FMUState) {
    Instance *self = (Instance *)instance;
    SavedState *saved = *FMUState ? (SavedState *)*FMUState : malloc(sizeof(SavedState));
    if (!saved) return fmi3Error;
    refresh_outputs(self);
    memcpy(saved->v, self->v, sizeof saved->v);
    saved->time = self->time;
    saved->mode = self->mode;
    *FMUState = saved;
    return fmi3OK;
}

fmi3Status fmi3SetFMUState(fmi3Instance instance, fmi3FMUState FMUState) {
    Instance *self = (Instance *)instance;
    SavedState *saved = (SavedState *)FMUState;
    memcpy(self->v, saved->v, sizeof self->v);
    self->time = saved->time;
    self->mode = saved->mode;
    self->outputs_stale = 0;
    return fmi3OK;
}

fmi3Status fmi3FreeFMUState(fmi3Instance instance, fmi3FMUState *FMUState) {
    (void)instance;
    free(*FMUState);
    *FMUState = NULL;
    return fmi3OK;
}

fmi3Status fmi3SerializedFMUStateSize(fmi3Instance instance, fmi3FMUState FMUState, size_t *size) {
    (void)instance; (void)FMUState;
    *size = sizeof(SavedState);
    return fmi3OK;
}

fmi3Status fmi3SerializeFMUState(fmi3Instance instance, fmi3FMUState FMUState,
                                 fmi3Byte serializedState[], size_t size) {
    if (size != sizeof(SavedState)) return unsupported(instance, "fmi3SerializeFMUState of that size");
    memcpy(serializedState, FMUState, sizeof(SavedState));
    return fmi3OK;
}

fmi3Status fmi3DeserializeFMUState(fmi3Instance instance, const fmi3Byte serializedState[],
                                   size_t size, fmi3FMUState *FMUState) {
    if (size != sizeof(SavedState)) return unsupported(instance, "fmi3DeserializeFMUState of that size");
    SavedState *saved = *FMUState ? (SavedState *)*FMUState : malloc(sizeof(SavedState));
    if (!saved) return fmi3Error;
    memcpy(saved, serializedState, sizeof(SavedState));
    *FMUState = saved;
    return fmi3OK;
}

fmi3Status fmi3EnterStepMode(fmi3Instance instance) { return unsupported(instance, "fmi3EnterStepMode"); }

/* ---- functions this FMU does not support: exported, refuse with a message ---- */
#define GETTER(NAME, TYPE)                                                                      \
    fmi3Status NAME(fmi3Instance instance, const fmi3ValueReference valueReferences[],          \
                    size_t nValueReferences, TYPE values[], size_t nValues) {                   \
        (void)valueReferences; (void)nValueReferences; (void)values; (void)nValues;             \
        return unsupported(instance, #NAME);                                                    \
    }
#define SETTER(NAME, TYPE)                                                                      \
    fmi3Status NAME(fmi3Instance instance, const fmi3ValueReference valueReferences[],          \
                    size_t nValueReferences, const TYPE values[], size_t nValues) {             \
        (void)valueReferences; (void)nValueReferences; (void)values; (void)nValues;             \
        return unsupported(instance, #NAME);                                                    \
    }
GETTER(fmi3GetFloat32, fmi3Float32)
GETTER(fmi3GetInt8, fmi3Int8)
GETTER(fmi3GetUInt8, fmi3UInt8)
GETTER(fmi3GetInt16, fmi3Int16)
GETTER(fmi3GetUInt16, fmi3UInt16)
GETTER(fmi3GetInt32, fmi3Int32)
GETTER(fmi3GetUInt32, fmi3UInt32)
GETTER(fmi3GetInt64, fmi3Int64)
GETTER(fmi3GetUInt64, fmi3UInt64)
GETTER(fmi3GetBoolean, fmi3Boolean)
GETTER(fmi3GetString, fmi3String)
SETTER(fmi3SetFloat32, fmi3Float32)
SETTER(fmi3SetInt8, fmi3Int8)
SETTER(fmi3SetUInt8, fmi3UInt8)
SETTER(fmi3SetInt16, fmi3Int16)
SETTER(fmi3SetUInt16, fmi3UInt16)
SETTER(fmi3SetInt32, fmi3Int32)
SETTER(fmi3SetUInt32, fmi3UInt32)
SETTER(fmi3SetInt64, fmi3Int64)
SETTER(fmi3SetUInt64, fmi3UInt64)
SETTER(fmi3SetBoolean, fmi3Boolean)
SETTER(fmi3SetString, fmi3String)

fmi3Status fmi3GetBinary(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                         size_t nValueReferences, size_t valueSizes[], fmi3Binary values[],
                         size_t nValues) {
    (void)valueReferences; (void)nValueReferences; (void)valueSizes; (void)values; (void)nValues;
    return unsupported(instance, "fmi3GetBinary");
}
fmi3Status fmi3SetBinary(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                         size_t nValueReferences, const size_t valueSizes[],
                         const fmi3Binary values[], size_t nValues) {
    (void)valueReferences; (void)nValueReferences; (void)valueSizes; (void)values; (void)nValues;
    return unsupported(instance, "fmi3SetBinary");
}
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
fmi3Status fmi3EvaluateDiscreteStates(fmi3Instance instance) { return unsupported(instance, "fmi3EvaluateDiscreteStates"); }
fmi3Status fmi3UpdateDiscreteStates(fmi3Instance instance, fmi3Boolean *discreteStatesNeedUpdate,
                                    fmi3Boolean *terminateSimulation,
                                    fmi3Boolean *nominalsOfContinuousStatesChanged,
                                    fmi3Boolean *valuesOfContinuousStatesChanged,
                                    fmi3Boolean *nextEventTimeDefined, fmi3Float64 *nextEventTime) {
    (void)discreteStatesNeedUpdate; (void)terminateSimulation; (void)nominalsOfContinuousStatesChanged;
    (void)valuesOfContinuousStatesChanged; (void)nextEventTimeDefined; (void)nextEventTime;
    return unsupported(instance, "fmi3UpdateDiscreteStates");
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
