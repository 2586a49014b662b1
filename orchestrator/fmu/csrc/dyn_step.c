/* The adapter's step helper: one call from Python does what a co-simulation step needs of an FMU,
 * SetReal (inputs), DoStep, GetReal (outputs) and GetFMUState (the state history keeps), reading
 * and writing the master's buffers in place. The step starts at p->t0 + t_ns nanoseconds (t_ns passed
 * as a pointer-sized integer: ctypes converts those fastest) and lasts p->h seconds.
 * It returns 0, or (call << 4 | status) for the first
 * call whose status is worse than Warning (or the first Warning when all passed):
 * call 1 set, 2 step, 3 get, 4 state; status 7 is an early return, 8 an output that is NaN or infinite
 * (the outputs are checked as they are read: the world need not), 9 a step that asked to end the
 * simulation (FMI 3's terminateSimulation on an OK step: kept, its outputs and state taken). */
#include <math.h>
#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

typedef struct {
    void *instance;
    void *set_real, *do_step, *get_real, *get_state;
    const unsigned *in_vr;
    size_t n_in_vr;
    const double *in;
    size_t n_in;
    const unsigned *out_vr;
    size_t n_out_vr;
    double *out;
    size_t n_out;
    int fmi3;
    int no_prior;
    double h;
    double t0;  /* the FMU's time at t_ns = 0 (its start time) */
    int *trace; /* when set: the number of the call under way (1 set .. 4 state), 0 between steps (isolation) */
} Plan;

typedef int (*set2_t)(void *, const unsigned *, size_t, const double *);
typedef int (*get2_t)(void *, const unsigned *, size_t, double *);
typedef int (*step2_t)(void *, double, double, int);
typedef int (*set3_t)(void *, const unsigned *, size_t, const double *, size_t);
typedef int (*get3_t)(void *, const unsigned *, size_t, double *, size_t);
typedef int (*step3_t)(void *, double, double, bool, bool *, bool *, bool *, double *);
typedef int (*state_t)(void *, void **);

#define CHECK(call, expr)                                      \
    do {                                                       \
        if (p->trace) *p->trace = (call);                      \
        int s_ = (expr);                                       \
        if (s_ > 1) return ((call) << 4) | s_;                 \
        if (s_ == 1 && !warn) warn = ((call) << 4) | 1;        \
    } while (0)

static int step_once(const Plan *p, void *t_ns, void **state) {
    int warn = 0;
    double t = p->t0 + (double)(uintptr_t)t_ns / 1e9, h = p->h;
    if (p->fmi3) {
        bool event = false, terminate = false, early = false;
        double last = 0.0;
        if (p->n_in_vr) CHECK(1, ((set3_t)p->set_real)(p->instance, p->in_vr, p->n_in_vr, p->in, p->n_in));
        CHECK(2, ((step3_t)p->do_step)(p->instance, t, h, p->no_prior != 0, &event, &terminate, &early, &last));
        if (early) return (2 << 4) | 7;
        if (terminate) warn = (2 << 4) | 9; /* a step that asks to end: kept, then the end is asked (ENDED) */
        if (p->n_out_vr) CHECK(3, ((get3_t)p->get_real)(p->instance, p->out_vr, p->n_out_vr, p->out, p->n_out));
    } else {
        if (p->n_in_vr) CHECK(1, ((set2_t)p->set_real)(p->instance, p->in_vr, p->n_in_vr, p->in));
        CHECK(2, ((step2_t)p->do_step)(p->instance, t, h, p->no_prior));
        if (p->n_out_vr) CHECK(3, ((get2_t)p->get_real)(p->instance, p->out_vr, p->n_out_vr, p->out));
    }
    for (size_t i = 0; i < p->n_out; ++i)
        if (!isfinite(p->out[i])) return (3 << 4) | 8;
    if (state) CHECK(4, ((state_t)p->get_state)(p->instance, state));
    return warn;
}

__attribute__((visibility("default"))) int dyn_step(const Plan *p, void *t_ns, void **state) {
    int rc = step_once(p, t_ns, state);
    if (p->trace) *p->trace = 0;
    return rc;
}

/* Several FMUs stepped as one (`orchestrator.fmu.fused`): for each member in schedule order, the bus
 * copies its inputs need (element runs of the bus, as the tick would make them), then `dyn_step`
 * with the state saved into states[i]. codes[i] gets the member's result; the first member whose
 * status is worse than Warning ends the call (the world rolls the tick back): its index plus one is
 * returned, and the members after it get 0. Otherwise the result is 0, or -1 when some member
 * warned (codes say which). One call from Python instead of one per member: about 0.4 us less per
 * FMU and step. */
typedef struct {
    size_t dst, src, n;
} Copy;

typedef struct {
    size_t n;
    const Plan *const *plans;
    const size_t *first_copy; /* member i's copies are copies[first_copy[i] .. first_copy[i + 1]) */
    const Copy *copies;
    double *bus;
    int *codes;
} Group;

__attribute__((visibility("default"))) int dyn_group(const Group *g, void *t_ns, void **states) {
    int warned = 0;
    for (size_t i = 0; i < g->n; ++i) {
        for (size_t c = g->first_copy[i]; c < g->first_copy[i + 1]; ++c) {
            const Copy *k = &g->copies[c];
            for (size_t j = 0; j < k->n; ++j) g->bus[k->dst + j] = g->bus[k->src + j];
        }
        int rc = dyn_step(g->plans[i], t_ns, states ? states + i : NULL);
        g->codes[i] = rc;
        if ((rc & 15) > 1 && (rc & 15) != 9) { /* (9: a kept step that asks to end, like a warning) */
            for (size_t j = i + 1; j < g->n; ++j) g->codes[j] = 0;
            return (int)i + 1;
        }
        if (rc) warned = 1;
    }
    return warned ? -1 : 0;
}
