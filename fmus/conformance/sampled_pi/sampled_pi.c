/* sampled_pi: a PI controller that runs at the ticks of its clock `sample` (see fmu.yaml). */
#include <math.h>

#include "fmu_model.h"

#define PERIOD 0.01 /* the interval of `sample`, seconds */

int model_init(ModelData *m) {
    m->u = 0.0;
    m->integral = 0.0;
    m->samples = 0;
    m->outside = 0;
    return MODEL_OK;
}

int model_step(ModelData *m, double h) {
    (void)m;
    (void)h;
    return MODEL_OK; /* between ticks nothing changes: the command is held */
}

int model_clock(ModelData *m, int clock) {
    if (clock == CLOCK_reset) {
        m->integral = 0.0;
        return MODEL_OK;
    }
    double e = m->r - m->y;
    m->integral += e * PERIOD;
    m->u = m->kp * e + m->ki * m->integral;
    m->samples += 1;
    int outside = fabs(e) > m->band;
    if (outside && !m->outside) fmu_tick(m, CLOCK_alarm);
    m->outside = outside;
    return MODEL_OK;
}
