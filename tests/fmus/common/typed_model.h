/* Interface between a test model (tests/fmus/<name>/model.c) and the typed
 * FMI 3.0 / FMI 2.0 Co-Simulation wrappers (fmi3_typed.c, fmi2_typed.c).
 *
 * Unlike the crusher/mill FMUs (fmus/common, all float64), a test model has
 * variables of any FMI type: scalars, and 1-D arrays of numbers and Booleans
 * (FMI 3 array variables; FMI 2 scalars name[1]..name[n]). fmus/typed.py generates variables.h from
 * tests/fmus/<name>/model.json: the struct ModelData (one field per
 * variable, named like it, plus `time`), the table VARIABLES the wrappers
 * use to get and set values by value reference, and set_start_values().
 * Strings are char[STRING_CAPACITY], Binary values unsigned char
 * [BINARY_CAPACITY] with a <name>_size field, Booleans and Enumerations the
 * FMI version's Boolean and integer types.
 */
#ifndef MINETWIN_TYPED_MODEL_H
#define MINETWIN_TYPED_MODEL_H

#include <stddef.h>
#include <stdint.h>

#define STRING_CAPACITY 256
#define BINARY_CAPACITY 256

enum { T_FLOAT32, T_FLOAT64, T_INT8, T_UINT8, T_INT16, T_UINT16, T_INT32, T_UINT32, T_INT64,
       T_UINT64, T_BOOLEAN, T_STRING, T_BINARY, T_ENUMERATION };
enum { C_INDEPENDENT, C_PARAMETER, C_INPUT, C_OUTPUT };

typedef struct {
    unsigned int vr;
    int type;
    int causality;
    size_t offset;       /* of the value in ModelData */
    size_t size_offset;  /* Binary: of the <name>_size field */
    size_t count;        /* elements: an FMI 3 array's size; 1 for scalars and FMI 2 elements */
    const char *name;
} VariableInfo;

#include "variables.h"

typedef enum { STEP_COMPLETE, STEP_EVENT, STEP_TERMINATE } StepResult;

/* Parameter checks when initialization ends: 0 if valid, else write a message
 * naming the parameter and its allowed range and return 1. */
int model_check(const ModelData *m, char *message, size_t size);

/* Outputs from parameters, inputs and states at m->time. */
void model_outputs(ModelData *m);

/* Advance m->time towards `end` with the inputs held. At an event, with
 * stop_at_events (FMI 3 event mode with early return) return STEP_EVENT at
 * the event's time before its update (the importer calls model_event_update
 * in event mode); without, apply model_event_update there and go on. Return
 * STEP_TERMINATE at the time the model requests the end of the simulation. */
StepResult model_advance(ModelData *m, double end, int stop_at_events);

/* Discrete update at an event; returns 1 if the model requests termination. */
int model_event_update(ModelData *m);

#endif
