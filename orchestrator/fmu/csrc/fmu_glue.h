/* Version-neutral core of the dynabrain FMU glue: the instance, the variable table, value access,
 * and FMU states (a saved state is a copy of ModelData). fmi2_glue.c and fmi3_glue.c map the FMI
 * 2.0 and 3.0 calls onto it. Internal to the FMU binary (hidden visibility). */
#ifndef DYNABRAIN_FMU_GLUE_H
#define DYNABRAIN_FMU_GLUE_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "fmu_model.h"

#if defined(__GNUC__)
#define GLUE_INTERNAL __attribute__((visibility("hidden")))
#else
#define GLUE_INTERNAL
#endif

/* How a variable is stored in ModelData (see fmu_model.h). */
typedef enum { T_REAL, T_INT, T_BOOL, T_F32, T_I8, T_U8, T_I16, T_U16, T_U32, T_I64, T_U64, T_ENUM, T_STR, T_BIN,
               T_CLOCK } VarType; /* a clock's `offset` is its number (CLOCK_<name>) */
/* How values cross the API: an FMI get/set function's value type. */
typedef enum { W_F64, W_F32, W_I8, W_U8, W_I16, W_U16, W_I32, W_U32, W_I64, W_U64, W_BOOL_INT, W_BOOL8, W_STR,
               W_BIN } Wire;
typedef enum { C_INDEPENDENT, C_PARAMETER, C_INPUT, C_OUTPUT, C_LOCAL } VarCausality;
typedef enum { V_CONSTANT, V_FIXED, V_TUNABLE, V_DISCRETE, V_CONTINUOUS } VarVariability;

/* One value reference: `count` values of `type` at `offset` in ModelData (a string or binary has
 * room for `capacity` bytes). */
typedef struct {
    unsigned char type, causality, variability, exact;
    size_t offset;
    size_t count;
    size_t capacity;
    const char *name;
} VarInfo;

typedef enum { MODE_INSTANTIATED, MODE_INIT, MODE_STEP, MODE_TERMINATED, MODE_ERROR, MODE_FATAL, MODE_EVENT } Mode;

/* A clock (FMI 3.0): an input clock the master activates (time-based with `interval` and `shift`
 * seconds, or triggered when `interval` is 0), or an output clock the model ticks (fmu_tick).
 * `kind` 1 tunable, 2 changing, 3 countdown: an input clock whose interval the model gives
 * (fmu_set_interval; kept in ModelData), 0 otherwise. */
typedef struct {
    int input;
    double interval, shift;
    int kind;
} ClockInfo;

struct Instance;
typedef void (*EmitFn)(struct Instance *inst, int status, const char *category, const char *message);

typedef struct Instance {
    ModelData d; /* first member: fmu_log() finds its instance from the model's data */
    Mode mode;
    bool logging;
    char *name;
    EmitFn emit;     /* the version's way to call the master's logger */
    void *env;       /* FMI 2: the callback functions; FMI 3: the instance environment */
    void *logger;    /* FMI 3: the log message callback */
    bool stop;       /* the model asked to end the simulation in the last step (fmu_stop) */
    bool event_mode_used;                 /* FMI 3: the master handles events (clocks) in event mode */
    unsigned char clock_active[NCLOCKS + 1]; /* in event mode: the clocks ticking now */
    unsigned char clock_done[NCLOCKS + 1];   /* ... and the input clocks model_clock has run for */
    bool early_allowed; /* FMI 3: the master handles an early return (earlyReturnAllowed) */
    bool early;         /* the model returned early from the last step (fmu_return_early), at d.time */
    void *clock_update; /* FMI 3 scheduled execution: the master's clock update callback (NULL: not one) */
} Instance;

/* A saved FMU state: the model data and the mode it was in. */
typedef struct {
    uint32_t magic;
    Mode mode;
    ModelData d;
} SavedState;

GLUE_INTERNAL Instance *core_new(const char *name, const char *token, EmitFn emit, void *env, void *logger,
                                 bool logging);
GLUE_INTERNAL void core_free(Instance *inst);
GLUE_INTERNAL void core_reset(Instance *inst);
GLUE_INTERNAL void core_log(Instance *inst, int status, const char *category, const char *format, ...)
#if defined(__GNUC__)
    __attribute__((format(printf, 4, 5)))
#endif
    ;
GLUE_INTERNAL int core_usable(Instance *inst, const char *call);
GLUE_INTERNAL int core_enter_init(Instance *inst, double start_time);
GLUE_INTERNAL int core_exit_init(Instance *inst);
GLUE_INTERNAL int core_do_step(Instance *inst, double t, double h);
GLUE_INTERNAL int core_terminate(Instance *inst);
/* value access: `values` is an array of the wire type (W_STR: const char *; W_BIN: const uint8_t *
 * with `sizes`, NULL otherwise) */
GLUE_INTERNAL int core_set(Instance *inst, Wire wire, const unsigned *vr, size_t nvr, const void *values,
                           const size_t *sizes, size_t nvalues, const char *call);
GLUE_INTERNAL int core_get(Instance *inst, Wire wire, const unsigned *vr, size_t nvr, void *values, size_t *sizes,
                           size_t nvalues, const char *call);
GLUE_INTERNAL int core_get_state(Instance *inst, void **state);
GLUE_INTERNAL int core_set_state(Instance *inst, void *state);
GLUE_INTERNAL int core_free_state(Instance *inst, void **state);
GLUE_INTERNAL size_t core_serialized_size(void);
GLUE_INTERNAL int core_serialize(Instance *inst, void *state, unsigned char *out, size_t size);
GLUE_INTERNAL int core_deserialize(Instance *inst, const unsigned char *in, size_t size, void **state);
GLUE_INTERNAL int core_unsupported(Instance *inst, const char *call);
/* FMI 3.0 event mode and clocks */
GLUE_INTERNAL int core_enter_event_mode(Instance *inst);
GLUE_INTERNAL bool core_event_pending(Instance *inst);
GLUE_INTERNAL int core_enter_step_mode(Instance *inst);
GLUE_INTERNAL int core_set_clock(Instance *inst, const unsigned *vr, size_t nvr, const bool *values);
GLUE_INTERNAL int core_get_clock(Instance *inst, const unsigned *vr, size_t nvr, bool *values);
GLUE_INTERNAL int core_update_discrete_states(Instance *inst, bool *terminate);
/* FMI 3 scheduled execution: run the partition of input clock `vr` now (its clock ticks alone) */
GLUE_INTERNAL int core_activate(Instance *inst, unsigned vr);
GLUE_INTERNAL int core_get_interval(Instance *inst, const unsigned *vr, size_t nvr, double *intervals, int *qualifiers);
GLUE_INTERNAL int core_get_shift(Instance *inst, const unsigned *vr, size_t nvr, double *shifts);

#endif
