/* Version-neutral core of the dynabrain FMU glue (see fmu_glue.h). */
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmu_glue.h"
#include "model_tables.inc" /* generated: MODEL_TOKEN, NVARS, VARS[], model_starts() */

#define STATE_MAGIC 0x53464244u  /* "DBFS" */
#define SERIAL_VERSION 1u

/* Serialized form: this header, then the ModelData bytes. */
typedef struct {
    uint32_t magic;
    uint32_t version;
    uint64_t data_size;
    uint64_t token_hash;
    int32_t mode;
    int32_t reserved;
} SerialHeader;

static uint64_t token_hash(void) {
    uint64_t h = 1469598103934665603ull; /* FNV-1a */
    for (const char *p = MODEL_TOKEN; *p; ++p) {
        h ^= (unsigned char)*p;
        h *= 1099511628211ull;
    }
    return h;
}

void fmu_log(const ModelData *m, int status, const char *format, ...) {
    Instance *inst = (Instance *)m;
    char message[1024];
    va_list args;
    va_start(args, format);
    vsnprintf(message, sizeof message, format, args);
    va_end(args);
    if (inst->emit) inst->emit(inst, status, status >= MODEL_WARNING ? "logStatusWarning" : "logEvents", message);
}

void fmu_stop(const ModelData *m, const char *format, ...) {
    Instance *inst = (Instance *)m;
    char message[1024];
    va_list args;
    va_start(args, format);
    vsnprintf(message, sizeof message, format, args);
    va_end(args);
    inst->stop = true;
    if (inst->emit) inst->emit(inst, MODEL_OK, "logEvents", message);
}

#if defined(__GNUC__)
__attribute__((weak))
#endif
int model_clock(ModelData *m, int clock) { /* a model without clocks needs none */
    (void)m;
    (void)clock;
    return MODEL_OK;
}

void fmu_tick(const ModelData *m, int clock) {
    Instance *inst = (Instance *)m;
    if (clock >= 0 && clock < NCLOCKS && !CLOCK_INFO[clock].input) inst->clock_active[clock] = 1;
}

void fmu_set_interval(const ModelData *m, int clock, double seconds) {
#ifdef FMU_DYNAMIC_CLOCKS
    ModelData *d = (ModelData *)m;
    if (clock < 0 || clock >= NCLOCKS || !CLOCK_INFO[clock].kind) return;
    d->fmu_interval_[clock] = seconds;
    d->fmu_interval_changed_[clock] = 1;
#else
    (void)m, (void)clock, (void)seconds;
#endif
}

int fmu_return_early(const ModelData *m, double t) {
    Instance *inst = (Instance *)m;
    if (!inst->early_allowed || !(t >= m->time)) return 0;
    inst->early = true;
    inst->d.time = t; /* the time the step reached (lastSuccessfulTime) */
    return 1;
}

void core_log(Instance *inst, int status, const char *category, const char *format, ...) {
    char message[1024];
    va_list args;
    if (!inst->emit || (status == MODEL_OK && !inst->logging)) return;
    va_start(args, format);
    vsnprintf(message, sizeof message, format, args);
    va_end(args);
    inst->emit(inst, status, category, message);
}

Instance *core_new(const char *name, const char *token, EmitFn emit, void *env, void *logger, bool logging) {
    Instance probe;
    memset(&probe, 0, sizeof probe);
    probe.emit = emit;
    probe.env = env;
    probe.logger = logger;
    probe.name = (char *)(name ? name : "?");
    if (!token || strcmp(token, MODEL_TOKEN) != 0) {
        core_log(&probe, MODEL_ERROR, "logStatusError", "instantiation token %s does not match this binary's %s",
                 token ? token : "(null)", MODEL_TOKEN);
        return NULL;
    }
    Instance *inst = calloc(1, sizeof *inst);
    char *copy = malloc(strlen(probe.name) + 1);
    if (!inst || !copy) {
        free(inst);
        free(copy);
        core_log(&probe, MODEL_ERROR, "logStatusError", "out of memory");
        return NULL;
    }
    strcpy(copy, probe.name);
    inst->name = copy;
    inst->emit = emit;
    inst->env = env;
    inst->logger = logger;
    inst->logging = logging;
    core_reset(inst);
    return inst;
}

void core_free(Instance *inst) {
    if (!inst) return;
    free(inst->name);
    free(inst);
}

void core_reset(Instance *inst) {
    memset(&inst->d, 0, sizeof inst->d);
    model_starts(&inst->d);
    inst->mode = MODE_INSTANTIATED;
    inst->stop = false;
    memset(inst->clock_active, 0, sizeof inst->clock_active);
    memset(inst->clock_done, 0, sizeof inst->clock_done);
}

int core_usable(Instance *inst, const char *call) {
    if (!inst) return MODEL_ERROR;
    if (inst->mode == MODE_FATAL) return MODEL_FATAL;
    if (inst->mode == MODE_ERROR) {
        core_log(inst, MODEL_ERROR, "logStatusError", "%s: the instance failed earlier; reset it or restore a state",
                 call);
        return MODEL_ERROR;
    }
    return MODEL_OK;
}

static int fail(Instance *inst, int status) {
    if (status == MODEL_ERROR) inst->mode = MODE_ERROR;
    if (status >= MODEL_FATAL) inst->mode = MODE_FATAL;
    return status;
}

int core_enter_init(Instance *inst, double start_time) {
    int s = core_usable(inst, "EnterInitializationMode");
    if (s) return s;
    if (inst->mode != MODE_INSTANTIATED) {
        core_log(inst, MODEL_ERROR, "logStatusError", "EnterInitializationMode: not in the instantiated state");
        return MODEL_ERROR;
    }
    inst->d.time = start_time;
    inst->mode = MODE_INIT;
    return MODEL_OK;
}

int core_exit_init(Instance *inst) {
    int s = core_usable(inst, "ExitInitializationMode");
    if (s) return s;
    if (inst->mode != MODE_INIT) {
        core_log(inst, MODEL_ERROR, "logStatusError", "ExitInitializationMode: not in initialization mode");
        return MODEL_ERROR;
    }
    s = model_init(&inst->d);
    if (s > MODEL_DISCARD) return fail(inst, s);
    if (s == MODEL_DISCARD) return MODEL_ERROR;
    inst->mode = inst->event_mode_used ? MODE_EVENT : MODE_STEP; /* FMI 3: initialization ends in event mode */
    return s;
}

int core_do_step(Instance *inst, double t, double h) {
    int s = core_usable(inst, "DoStep");
    if (s) return s;
    if (inst->mode != MODE_STEP) {
        core_log(inst, MODEL_ERROR, "logStatusError", "DoStep: the instance is not initialized");
        return MODEL_ERROR;
    }
    if (!(h > 0.0)) {
        core_log(inst, MODEL_ERROR, "logStatusError", "DoStep: step size %g is not positive", h);
        return MODEL_ERROR;
    }
    inst->d.time = t;
    inst->stop = false;
    inst->early = false;
    s = model_step(&inst->d, h);
    if (s <= MODEL_WARNING && inst->early && inst->d.time < t + h) return s; /* ended early, at d.time */
    inst->early = false;
    if (s <= MODEL_WARNING) inst->d.time = t + h;
    else if (s > MODEL_DISCARD) return fail(inst, s);
    return s;
}

int core_terminate(Instance *inst) {
    int s = core_usable(inst, "Terminate");
    if (s) return s;
    inst->mode = MODE_TERMINATED;
    return MODEL_OK;
}

static int settable(const Instance *inst, const VarInfo *v) {
    bool before_step = inst->mode == MODE_INSTANTIATED || inst->mode == MODE_INIT;
    switch (v->causality) {
    case C_INPUT: return inst->mode != MODE_TERMINATED;
    case C_PARAMETER: return v->variability == V_TUNABLE ? inst->mode != MODE_TERMINATED : before_step;
    case C_LOCAL: return v->exact && before_step;
    default: return 0;
    }
}

static const char *wire_name(Wire w) {
    static const char *names[] = {"Float64", "Float32", "Int8", "UInt8", "Int16", "UInt16", "Int32", "UInt32",
                                  "Int64", "UInt64", "Boolean", "Boolean", "String", "Binary"};
    return names[w];
}

/* Whether values of wire type `w` reach variables stored as `t` (an enumeration is an Int32 in FMI 2
 * and an Int64 in FMI 3; a boolean is an int in FMI 2 and a 1-byte bool in FMI 3). */
static int compatible(Wire w, VarType t) {
    switch (w) {
    case W_F64: return t == T_REAL;
    case W_F32: return t == T_F32;
    case W_I8: return t == T_I8;
    case W_U8: return t == T_U8;
    case W_I16: return t == T_I16;
    case W_U16: return t == T_U16;
    case W_I32: return t == T_INT || t == T_ENUM;
    case W_U32: return t == T_U32;
    case W_I64: return t == T_I64 || t == T_ENUM;
    case W_U64: return t == T_U64;
    case W_BOOL_INT: case W_BOOL8: return t == T_BOOL;
    case W_STR: return t == T_STR;
    case W_BIN: return t == T_BIN;
    }
    return 0;
}

/* Whether values go between the wire and the field as they are (same type, same layout). */
static int plain(Wire w, VarType t) {
    return w != W_BOOL_INT && w != W_BOOL8 && w != W_STR && w != W_BIN && !(t == T_ENUM && w == W_I64);
}

/* Copy `count` values of `width` bytes (constant-size copies: a store each, no call). */
static inline void copy_values(char *dst, const char *src, size_t width, size_t count) {
    switch (width) {
    case 8: for (size_t i = 0; i < count; ++i) memcpy(dst + 8 * i, src + 8 * i, 8); break;
    case 4: for (size_t i = 0; i < count; ++i) memcpy(dst + 4 * i, src + 4 * i, 4); break;
    case 2: for (size_t i = 0; i < count; ++i) memcpy(dst + 2 * i, src + 2 * i, 2); break;
    default: memcpy(dst, src, width * count);
    }
}

static size_t wire_size(Wire w) {
    static const size_t sizes[] = {sizeof(double), sizeof(float), 1, 1, 2, 2, 4, 4, 8, 8, sizeof(int), sizeof(bool),
                                   sizeof(const char *), sizeof(const uint8_t *)};
    return sizes[w];
}

static const VarInfo *lookup(Instance *inst, Wire wire, unsigned vr, const char *call) {
    if (vr >= NVARS) {
        core_log(inst, MODEL_ERROR, "logStatusError", "%s: unknown value reference %u", call, vr);
        return NULL;
    }
    const VarInfo *v = &VARS[vr];
    if (!compatible(wire, (VarType)v->type)) {
        core_log(inst, MODEL_ERROR, "logStatusError", "%s: variable %s (value reference %u) is not of type %s", call,
                 v->name, vr, wire_name(wire));
        return NULL;
    }
    return v;
}

/* Check every reference, every value and the value count before touching anything: a refused call
 * changes nothing. */
static int plan_access(Instance *inst, Wire wire, const unsigned *vr, size_t nvr, const void *values,
                       const size_t *sizes, size_t nvalues, bool set, const char *call) {
    size_t total = 0;
    for (size_t i = 0; i < nvr; ++i) {
        const VarInfo *v = lookup(inst, wire, vr[i], call);
        if (!v) return MODEL_ERROR;
        if (set && !settable(inst, v)) {
            core_log(inst, MODEL_ERROR, "logStatusError", "%s: variable %s cannot be set now", call, v->name);
            return MODEL_ERROR;
        }
        bool checked = v->type == T_STR || v->type == T_BIN || (v->type == T_ENUM && wire == W_I64);
        for (size_t j = 0; set && checked && j < v->count && total + j < nvalues; ++j) {
            size_t k = total + j;
            if (v->type == T_ENUM) {
                int64_t x = wire == W_I64 ? ((const int64_t *)values)[k] : ((const int32_t *)values)[k];
                if (x < INT32_MIN || x > INT32_MAX) {
                    core_log(inst, MODEL_ERROR, "logStatusError", "%s: %lld is not a value of enumeration %s", call,
                             (long long)x, v->name);
                    return MODEL_ERROR;
                }
            } else if (v->type == T_STR) {
                const char *text = ((const char *const *)values)[k];
                if (!text || strlen(text) >= v->capacity) {
                    core_log(inst, MODEL_ERROR, "logStatusError", "%s: a string of %zu bytes does not fit %s (at most "
                             "%zu)", call, text ? strlen(text) : 0, v->name, v->capacity - 1);
                    return MODEL_ERROR;
                }
            } else if (v->type == T_BIN) {
                if (!sizes || sizes[k] > v->capacity || (sizes[k] && !((const uint8_t *const *)values)[k])) {
                    core_log(inst, MODEL_ERROR, "logStatusError", "%s: %zu bytes do not fit %s (at most %zu)", call,
                             sizes ? sizes[k] : 0, v->name, v->capacity);
                    return MODEL_ERROR;
                }
            }
        }
        total += v->count;
    }
    if (total != nvalues) {
        core_log(inst, MODEL_ERROR, "logStatusError", "%s: %zu values given for %zu", call, nvalues, total);
        return MODEL_ERROR;
    }
    return MODEL_OK;
}

typedef FMU_BINARY(1) BinaryHead; /* every binary field starts so, whatever its capacity */
#define BINARY_DATA(field) ((uint8_t *)(field) + offsetof(BinaryHead, data))

/* Reals: the step's own calls, kept as short as they can be. */
static int reals_ok(Instance *inst, const unsigned *vr, size_t nvr, size_t nvalues, bool set, const char *call) {
    size_t total = 0;
    for (size_t i = 0; i < nvr; ++i) {
        if (vr[i] >= NVARS || VARS[vr[i]].type != T_REAL) return plan_access(inst, W_F64, vr, nvr, NULL, NULL, nvalues,
                                                                             set, call);
        if (set && !settable(inst, &VARS[vr[i]])) return plan_access(inst, W_F64, vr, nvr, NULL, NULL, nvalues, set, call);
        total += VARS[vr[i]].count;
    }
    return total == nvalues ? MODEL_OK : plan_access(inst, W_F64, vr, nvr, NULL, NULL, nvalues, set, call);
}

static int set_reals(Instance *inst, const unsigned *vr, size_t nvr, const double *values, size_t nvalues,
                     const char *call) {
    int s = core_usable(inst, call);
    if (s) return s;
    if (nvr && (!vr || !values)) return MODEL_ERROR;
    s = reals_ok(inst, vr, nvr, nvalues, true, call);
    if (s) return s;
    char *base = (char *)&inst->d;
    for (size_t i = 0, k = 0; i < nvr; ++i) {
        const VarInfo *v = &VARS[vr[i]];
        for (size_t j = 0; j < v->count; ++j, ++k) ((double *)(base + v->offset))[j] = values[k];
    }
    return MODEL_OK;
}

static int get_reals(Instance *inst, const unsigned *vr, size_t nvr, double *values, size_t nvalues,
                     const char *call) {
    int s = core_usable(inst, call);
    if (s) return s;
    if (nvr && (!vr || !values)) return MODEL_ERROR;
    s = reals_ok(inst, vr, nvr, nvalues, false, call);
    if (s) return s;
    const char *base = (const char *)&inst->d;
    for (size_t i = 0, k = 0; i < nvr; ++i) {
        const VarInfo *v = &VARS[vr[i]];
        for (size_t j = 0; j < v->count; ++j, ++k) values[k] = ((const double *)(base + v->offset))[j];
    }
    return MODEL_OK;
}

int core_set(Instance *inst, Wire wire, const unsigned *vr, size_t nvr, const void *values, const size_t *sizes,
             size_t nvalues, const char *call) {
    if (wire == W_F64) return set_reals(inst, vr, nvr, values, nvalues, call);
    int s = core_usable(inst, call);
    if (s) return s;
    if (nvr && (!vr || !values)) return MODEL_ERROR;
    s = plan_access(inst, wire, vr, nvr, values, sizes, nvalues, true, call);
    if (s) return s;
    size_t k = 0, width = wire_size(wire);
    char *base = (char *)&inst->d;
    for (size_t i = 0; i < nvr; ++i) {
        const VarInfo *v = &VARS[vr[i]];
        char *field = base + v->offset;
        if (plain(wire, (VarType)v->type)) { /* numbers: one copy for the whole variable */
            copy_values(field, (const char *)values + k * width, width, v->count);
            k += v->count;
            continue;
        }
        for (size_t j = 0; j < v->count; ++j, ++k) {
            const char *src = (const char *)values + k * width;
            if (wire == W_BOOL_INT) ((int32_t *)field)[j] = *(const int *)src != 0;
            else if (wire == W_BOOL8) ((int32_t *)field)[j] = *(const bool *)src;
            else if (v->type == T_ENUM) ((int32_t *)field)[j] = wire == W_I64 ? (int32_t)*(const int64_t *)src
                                                                            : *(const int32_t *)src;
            else if (wire == W_STR) strcpy(field, *(const char *const *)src);
            else if (wire == W_BIN) {
                ((BinaryHead *)field)->size = (uint32_t)sizes[k];
                if (sizes[k]) memcpy(BINARY_DATA(field), *(const uint8_t *const *)src, sizes[k]);
            } else memcpy(field + j * width, src, width);
        }
    }
    return MODEL_OK;
}

int core_get(Instance *inst, Wire wire, const unsigned *vr, size_t nvr, void *values, size_t *sizes, size_t nvalues,
             const char *call) {
    if (wire == W_F64) return get_reals(inst, vr, nvr, values, nvalues, call);
    int s = core_usable(inst, call);
    if (s) return s;
    if (nvr && (!vr || !values || (wire == W_BIN && !sizes))) return MODEL_ERROR;
    s = plan_access(inst, wire, vr, nvr, values, sizes, nvalues, false, call);
    if (s) return s;
    size_t k = 0, width = wire_size(wire);
    char *base = (char *)&inst->d;
    for (size_t i = 0; i < nvr; ++i) {
        const VarInfo *v = &VARS[vr[i]];
        char *field = base + v->offset;
        if (plain(wire, (VarType)v->type)) {
            copy_values((char *)values + k * width, field, width, v->count);
            k += v->count;
            continue;
        }
        for (size_t j = 0; j < v->count; ++j, ++k) {
            char *dst = (char *)values + k * width;
            if (wire == W_BOOL_INT) *(int *)dst = ((const int32_t *)field)[j] != 0;
            else if (wire == W_BOOL8) *(bool *)dst = ((const int32_t *)field)[j] != 0;
            else if (v->type == T_ENUM && wire == W_I64) *(int64_t *)dst = ((const int32_t *)field)[j];
            else if (wire == W_STR) *(const char **)dst = field;
            else if (wire == W_BIN) {
                *(const uint8_t **)dst = BINARY_DATA(field);
                sizes[k] = ((BinaryHead *)field)->size;
            } else memcpy(dst, field + j * width, width);
        }
    }
    return MODEL_OK;
}

static SavedState *checked(Instance *inst, void *state, const char *call) {
    SavedState *s = state;
    if (!s || s->magic != STATE_MAGIC) {
        core_log(inst, MODEL_ERROR, "logStatusError", "%s: not an FMU state of this FMU", call);
        return NULL;
    }
    return s;
}

/* A non-NULL *state is a state returned before: it is overwritten in place (no allocation). */
int core_get_state(Instance *inst, void **state) {
    int s = core_usable(inst, "GetFMUState");
    if (s) return s;
    if (!state) return MODEL_ERROR;
    SavedState *saved = *state;
    if (saved && !checked(inst, saved, "GetFMUState")) return MODEL_ERROR;
    if (!saved) {
        saved = malloc(sizeof *saved);
        if (!saved) {
            core_log(inst, MODEL_ERROR, "logStatusError", "GetFMUState: out of memory");
            return MODEL_ERROR;
        }
        *state = saved;
    }
    saved->magic = STATE_MAGIC;
    saved->mode = inst->mode;
    memcpy(&saved->d, &inst->d, sizeof inst->d);
    return MODEL_OK;
}

int core_set_state(Instance *inst, void *state) {
    if (!inst) return MODEL_ERROR;
    if (inst->mode == MODE_FATAL) return MODEL_FATAL;
    SavedState *saved = checked(inst, state, "SetFMUState");
    if (!saved) return MODEL_ERROR;
    memcpy(&inst->d, &saved->d, sizeof inst->d);
    inst->mode = saved->mode;
    inst->stop = false;
    memset(inst->clock_active, 0, sizeof inst->clock_active);
    memset(inst->clock_done, 0, sizeof inst->clock_done);
    return MODEL_OK;
}

int core_free_state(Instance *inst, void **state) {
    if (!state || !*state) return MODEL_OK;
    if (!checked(inst, *state, "FreeFMUState")) return MODEL_ERROR;
    ((SavedState *)*state)->magic = 0;
    free(*state);
    *state = NULL;
    return MODEL_OK;
}

size_t core_serialized_size(void) { return sizeof(SerialHeader) + sizeof(ModelData); }

int core_serialize(Instance *inst, void *state, unsigned char *out, size_t size) {
    SavedState *saved = checked(inst, state, "SerializeFMUState");
    if (!saved) return MODEL_ERROR;
    if (!out || size < core_serialized_size()) {
        core_log(inst, MODEL_ERROR, "logStatusError", "SerializeFMUState: buffer of %zu bytes, %zu needed", size,
                 core_serialized_size());
        return MODEL_ERROR;
    }
    SerialHeader h = {STATE_MAGIC, SERIAL_VERSION, sizeof(ModelData), token_hash(), (int32_t)saved->mode, 0};
    memcpy(out, &h, sizeof h);
    memcpy(out + sizeof h, &saved->d, sizeof saved->d);
    return MODEL_OK;
}

int core_deserialize(Instance *inst, const unsigned char *in, size_t size, void **state) {
    SerialHeader h;
    if (!in || !state || size != core_serialized_size()) {
        core_log(inst, MODEL_ERROR, "logStatusError", "DeserializeFMUState: %zu bytes, %zu expected", size,
                 core_serialized_size());
        return MODEL_ERROR;
    }
    memcpy(&h, in, sizeof h);
    if (h.magic != STATE_MAGIC || h.version != SERIAL_VERSION || h.data_size != sizeof(ModelData) ||
        h.token_hash != token_hash()) {
        core_log(inst, MODEL_ERROR, "logStatusError", "DeserializeFMUState: the bytes are not a state of this FMU");
        return MODEL_ERROR;
    }
    SavedState *saved = *state;
    if (saved && !checked(inst, saved, "DeserializeFMUState")) return MODEL_ERROR;
    if (!saved) {
        saved = malloc(sizeof *saved);
        if (!saved) return MODEL_ERROR;
        *state = saved;
    }
    saved->magic = STATE_MAGIC;
    saved->mode = (Mode)h.mode;
    memcpy(&saved->d, in + sizeof h, sizeof saved->d);
    return MODEL_OK;
}

int core_unsupported(Instance *inst, const char *call) {
    if (inst) core_log(inst, MODEL_ERROR, "logStatusError", "%s is not supported by this FMU", call);
    return MODEL_ERROR;
}

/* -- FMI 3.0 event mode and clocks ------------------------------------------------------------------ */
static int in_mode(Instance *inst, Mode mode, const char *call) {
    int s = core_usable(inst, call);
    if (s) return s;
    if (inst->mode != mode) {
        core_log(inst, MODEL_ERROR, "logStatusError", "%s: not in %s mode", call, mode == MODE_EVENT ? "event" : "step");
        return MODEL_ERROR;
    }
    return MODEL_OK;
}

/* Deactivate the input clocks (and the output clocks too when `outputs`). */
static void clear_clocks(Instance *inst, bool outputs) {
    for (int c = 0; c < NCLOCKS; ++c) {
        if (outputs || CLOCK_INFO[c].input) inst->clock_active[c] = 0;
        inst->clock_done[c] = 0;
    }
}

/* Whether an output clock ticked (in model_step: the master must handle the event). */
bool core_event_pending(Instance *inst) {
    for (int c = 0; c < NCLOCKS; ++c)
        if (!CLOCK_INFO[c].input && inst->clock_active[c]) return true;
    return false;
}

int core_enter_event_mode(Instance *inst) {
    int s = in_mode(inst, MODE_STEP, "EnterEventMode");
    if (s) return s;
    inst->mode = MODE_EVENT;
    clear_clocks(inst, false); /* output clocks ticked by the last step stay for GetClock */
    return MODEL_OK;
}

int core_enter_step_mode(Instance *inst) {
    int s = in_mode(inst, MODE_EVENT, "EnterStepMode");
    if (s) return s;
    inst->mode = MODE_STEP;
    clear_clocks(inst, true);
    return MODEL_OK;
}

/* The clock number of value reference `vr`, or -1 (said why). */
static int clock_of(Instance *inst, unsigned vr, const char *call) {
    if (vr >= NVARS || VARS[vr].type != T_CLOCK) {
        core_log(inst, MODEL_ERROR, "logStatusError", "%s: value reference %u is not a clock", call, vr);
        return -1;
    }
    return (int)VARS[vr].offset;
}

int core_set_clock(Instance *inst, const unsigned *vr, size_t nvr, const bool *values) {
    int s = in_mode(inst, MODE_EVENT, "SetClock");
    if (s) return s;
    for (size_t i = 0; i < nvr; ++i) {
        int c = clock_of(inst, vr[i], "SetClock");
        if (c < 0) return MODEL_ERROR;
        if (!CLOCK_INFO[c].input) {
            core_log(inst, MODEL_ERROR, "logStatusError", "SetClock: %s is an output clock", VARS[vr[i]].name);
            return MODEL_ERROR;
        }
    }
    for (size_t i = 0; i < nvr; ++i) {
        int c = (int)VARS[vr[i]].offset;
        inst->clock_active[c] = values[i] ? 1 : 0;
#ifdef FMU_DYNAMIC_CLOCKS
        if (values[i] && CLOCK_INFO[c].kind == 3) { /* a countdown ran out: no next one until the model says */
            inst->d.fmu_interval_[c] = 0.0;
            inst->d.fmu_interval_changed_[c] = 0;
        }
#endif
    }
    return MODEL_OK;
}

int core_get_clock(Instance *inst, const unsigned *vr, size_t nvr, bool *values) {
    int s = in_mode(inst, MODE_EVENT, "GetClock");
    if (s) return s;
    for (size_t i = 0; i < nvr; ++i) {
        int c = clock_of(inst, vr[i], "GetClock");
        if (c < 0) return MODEL_ERROR;
        values[i] = inst->clock_active[c] != 0;
        if (!CLOCK_INFO[c].input) inst->clock_active[c] = 0; /* an output clock is reset by reading it */
    }
    return MODEL_OK;
}

int core_update_discrete_states(Instance *inst, bool *terminate) {
    int s = in_mode(inst, MODE_EVENT, "UpdateDiscreteStates");
    if (s) return s;
    int worst = MODEL_OK;
    inst->stop = false;
    for (int c = 0; c < NCLOCKS; ++c) {
        if (!CLOCK_INFO[c].input || !inst->clock_active[c] || inst->clock_done[c]) continue;
        inst->clock_done[c] = 1;
        s = model_clock(&inst->d, c);
        if (s > MODEL_DISCARD) return fail(inst, s);
        if (s == MODEL_DISCARD) return MODEL_ERROR; /* no step to discard in event mode */
        if (s > worst) worst = s;
    }
    if (terminate) *terminate = inst->stop;
    return worst;
}

int core_activate(Instance *inst, unsigned vr) {
    const bool on = true;
    int s = core_set_clock(inst, &vr, 1, &on);
    if (s) return s;
    int c = (int)VARS[vr].offset;
    inst->clock_done[c] = 0;
    bool terminate = false;
    s = core_update_discrete_states(inst, &terminate);
    inst->clock_active[c] = 0; /* the partition ran: its clock is inactive again */
    inst->clock_done[c] = 0;
    if (s <= MODEL_WARNING && terminate) {
        core_log(inst, MODEL_ERROR, "logStatusError", "the model asked to end the simulation at t=%g s", inst->d.time);
        return MODEL_ERROR;
    }
    return s;
}

int core_get_interval(Instance *inst, const unsigned *vr, size_t nvr, double *intervals, int *qualifiers) {
    int s = core_usable(inst, "GetIntervalDecimal");
    if (s) return s;
    for (size_t i = 0; i < nvr; ++i) {
        int c = clock_of(inst, vr[i], "GetIntervalDecimal");
        if (c < 0) return MODEL_ERROR;
        intervals[i] = CLOCK_INFO[c].interval;
        qualifiers[i] = CLOCK_INFO[c].interval > 0 ? 1 /* fmi3IntervalUnchanged */ : 0 /* NotYetKnown */;
#ifdef FMU_DYNAMIC_CLOCKS
        if (CLOCK_INFO[c].kind) { /* given by the model: fmi3IntervalChanged once, then Unchanged */
            intervals[i] = inst->d.fmu_interval_[c];
            qualifiers[i] = inst->d.fmu_interval_changed_[c] ? 2 : (intervals[i] > 0 ? 1 : 0);
            inst->d.fmu_interval_changed_[c] = 0;
        }
#endif
    }
    return MODEL_OK;
}

int core_get_shift(Instance *inst, const unsigned *vr, size_t nvr, double *shifts) {
    int s = core_usable(inst, "GetShiftDecimal");
    if (s) return s;
    for (size_t i = 0; i < nvr; ++i) {
        int c = clock_of(inst, vr[i], "GetShiftDecimal");
        if (c < 0) return MODEL_ERROR;
        shifts[i] = CLOCK_INFO[c].shift;
    }
    return MODEL_OK;
}
