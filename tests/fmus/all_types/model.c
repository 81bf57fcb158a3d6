/* Every-type test model: y_<type> is a fixed function of p_<type> and
 * u_<type> in that type's own C arithmetic (integers wrap as C does; the
 * tests stay in range): numbers p + u (Float64: p + u * time), Boolean
 * u xor p, String and Binary p followed by u (truncated to the capacity),
 * Enumeration Level (u + p - 2) mod 3 + 1; arrays: Int32[3] 2 u + p_int32,
 * Boolean[2] not u (FMI 2: elements name[1]..). FMI 2 has the Real, Integer,
 * Boolean, String and Enumeration variables only. */
#include <stdio.h>
#include <string.h>

#include "typed_model.h"

int model_check(const ModelData *m, char *message, size_t size) {
    if (m->p_enumeration < 1 || m->p_enumeration > 3) {
        snprintf(message, size, "p_enumeration = %lld: must be a Level item, 1..3",
                 (long long)m->p_enumeration);
        return 1;
    }
    return 0;
}

void model_outputs(ModelData *m) {
    m->y_float64 = m->p_float64 + m->u_float64 * m->time;
    m->y_int32 = m->p_int32 + m->u_int32;
    m->y_boolean = (m->u_boolean != 0) != (m->p_boolean != 0);
    size_t head_text = strlen(m->p_string);  /* both shorter than STRING_CAPACITY */
    size_t tail_text = strlen(m->u_string);
    if (head_text + tail_text >= STRING_CAPACITY) tail_text = STRING_CAPACITY - 1 - head_text;
    memcpy(m->y_string, m->p_string, head_text);
    memcpy(m->y_string + head_text, m->u_string, tail_text);
    m->y_string[head_text + tail_text] = '\0';
    m->y_enumeration = (m->u_enumeration + m->p_enumeration - 2) % 3 + 1;
    for (int i = 0; i < 3; i++) m->y_int32_array[i] = 2 * m->u_int32_array[i] + m->p_int32;
    for (int i = 0; i < 2; i++) m->y_boolean_array[i] = !m->u_boolean_array[i];
#if FMI_VERSION == 3
    m->y_float32 = m->p_float32 + m->u_float32;
    m->y_int8 = (int8_t)(m->p_int8 + m->u_int8);
    m->y_uint8 = (uint8_t)(m->p_uint8 + m->u_uint8);
    m->y_int16 = (int16_t)(m->p_int16 + m->u_int16);
    m->y_uint16 = (uint16_t)(m->p_uint16 + m->u_uint16);
    m->y_uint32 = m->p_uint32 + m->u_uint32;
    m->y_int64 = m->p_int64 + m->u_int64;
    m->y_uint64 = m->p_uint64 + m->u_uint64;
    size_t head = m->p_binary_size;
    size_t tail = m->u_binary_size;
    if (head + tail > BINARY_CAPACITY) tail = BINARY_CAPACITY - head;
    memcpy(m->y_binary, m->p_binary, head);
    memcpy(m->y_binary + head, m->u_binary, tail);
    m->y_binary_size = head + tail;
#endif
}

StepResult model_advance(ModelData *m, double end, int stop_at_events) {
    (void)stop_at_events;
    m->time = end;
    return STEP_COMPLETE;
}

int model_event_update(ModelData *m) {
    (void)m;
    return 0;
}
