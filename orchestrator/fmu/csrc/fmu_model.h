/* The model interface of a dynabrain C FMU: what a model author writes against.
 *
 * A model is a struct of plain values, `ModelData`, generated from the FMU's fmu.yaml into
 * model_data.h: `time`, one field per variable (an array for a variable with `size`) and the extra
 * fields of `c_state`. Everything that changes while the FMU runs lives in it, so the glue saves,
 * restores and serializes the FMU state by copying it: a model needs no code for that, and must
 * keep no state anywhere else (no globals, no pointers into the heap).
 *
 * The glue (fmi2_glue.c, fmi3_glue.c, fmu_core.c) implements the FMI 2.0 and 3.0 co-simulation
 * API on top of two hooks:
 *
 *   model_init(m)      after the start values, parameters and inputs are set (end of
 *                      initialization mode): compute the outputs at m->time;
 *   model_step(m, h)   advance from m->time to m->time + h using the inputs; write the outputs.
 *                      The glue sets m->time before and after the call.
 *
 * Both return one of the MODEL_* codes (the FMI status numbering): MODEL_DISCARD refuses the step
 * (the master may roll back and retry), MODEL_ERROR fails the instance until it is reset or a saved
 * state is restored, MODEL_FATAL ends it. Say why with fmu_log() before returning anything but OK.
 * A model that has reached its end (a tank empty, a game over) calls fmu_stop() in model_step and
 * returns MODEL_OK: the master is asked to end the simulation there (FMI 3.0: terminateSimulation;
 * FMI 2.0: fmi2Discard, and fmi2GetBooleanStatus(fmi2Terminated) says true). An FMI 3.0 model with
 * clocks also implements model_clock (below): the master runs it in event mode at each tick.
 *
 * Field types (fmu.yaml `type:`): real double, float32 float, int8..uint64 the <stdint.h> types,
 * integer int32_t, boolean int32_t (0 or 1), enumeration int32_t (1..the number of items), string
 * char[capacity] (NUL-terminated), binary FmuBinary with `capacity` bytes of data.
 */
#ifndef DYNABRAIN_FMU_MODEL_H
#define DYNABRAIN_FMU_MODEL_H

#include <stdint.h>

/* A binary variable: `size` bytes of `data` are its value (the generated field has room for the
 * variable's `capacity`). */
#define FMU_BINARY(capacity) struct { uint32_t size; uint8_t data[capacity]; }

#include "model_data.h" /* generated from fmu.yaml */

enum { MODEL_OK = 0, MODEL_WARNING = 1, MODEL_DISCARD = 2, MODEL_ERROR = 3, MODEL_FATAL = 4 };

int model_init(ModelData *m);
int model_step(ModelData *m, double h);

/* FMI 3.0 clocks (fmu.yaml `clocks:`; CLOCK_<name> numbers them): called in event mode for each
 * input clock that ticks, after the clocked inputs are set; it updates clocked variables and may
 * tick output clocks with fmu_tick(). A model without clocks need not define it. */
int model_clock(ModelData *m, int clock);

/* Tick an output clock (in model_clock). */
void fmu_tick(const ModelData *m, int clock);

/* The interval of a tunable, changing or countdown input clock (fmu.yaml `variability:`), in seconds,
 * counted from now: in model_init (the first tick), and in model_clock (tunable: a new period from
 * this event on; changing: the time to the next tick, given at each tick; countdown: start a
 * countdown, the clock ticks once when it runs out). The master reads it after the event. */
void fmu_set_interval(const ModelData *m, int clock, double seconds);

/* In model_step, at an event inside the step (a threshold crossed, an output clock ticked): whether
 * the master lets the step end there (FMI 3.0 early return). If it returns 1, the model has advanced
 * itself to time `t` (from m->time up to the step's end) and returns MODEL_OK: the glue reports the
 * step as ended at `t`, the master handles the event there and steps on from `t`. If 0, the model
 * goes on to the step's end. */
int fmu_return_early(const ModelData *m, double t);

/* Log a message through the master's logger (printf format). */
void fmu_log(const ModelData *m, int status, const char *format, ...)
#if defined(__GNUC__)
    __attribute__((format(printf, 3, 4)))
#endif
    ;

/* Ask the master to end the simulation after this step (say why, printf format). */
void fmu_stop(const ModelData *m, const char *format, ...)
#if defined(__GNUC__)
    __attribute__((format(printf, 2, 3)))
#endif
    ;

#endif
