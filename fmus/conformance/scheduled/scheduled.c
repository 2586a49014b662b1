/* scheduled: model partitions of periodic, triggered, countdown and tunable input clocks (see fmu.yaml). */
#include "fmu_model.h"

int model_init(ModelData *m) {
    m->ticks = m->resets = m->laters = m->beats = m->thirds = 0;
    m->total = 0.0;
    m->t_later = m->t_beat = -1.0;
    m->period_now = m->period;
    fmu_set_interval(m, CLOCK_beat, m->period);
    return MODEL_OK;
}

int model_step(ModelData *m, double h) { /* no steps in scheduled execution */
    (void)m, (void)h;
    return MODEL_OK;
}

int model_clock(ModelData *m, int clock) {
    if (clock == CLOCK_tick) {
        m->ticks += 1;
        m->total += m->gain;
        if (m->ticks % 3 == 0) {
            m->thirds += 1;
            fmu_tick(m, CLOCK_third);
        }
    } else if (clock == CLOCK_reset) {
        m->resets += 1;
        m->ticks = 0;
        fmu_set_interval(m, CLOCK_later, m->delay);
    } else if (clock == CLOCK_later) {
        m->laters += 1;
        m->t_later = m->time;
    } else if (clock == CLOCK_beat) {
        m->beats += 1;
        m->t_beat = m->time;
        if (m->period != m->period_now) {
            m->period_now = m->period;
            fmu_set_interval(m, CLOCK_beat, m->period);
        }
    }
    return MODEL_OK;
}
