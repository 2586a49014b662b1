/* aperiodic: a tunable, a changing and a countdown input clock (see fmu.yaml). */
#include "fmu_model.h"

int model_init(ModelData *m) {
    m->beats = m->chirps = m->alarms = 0;
    m->t_beat = m->t_chirp = m->t_alarm = -1.0;
    m->period_now = m->period;
    fmu_set_interval(m, CLOCK_beat, m->period);
    fmu_set_interval(m, CLOCK_chirp, 0.01); /* the first chirp 10 ms after the start */
    return MODEL_OK;
}

int model_step(ModelData *m, double h) {
    (void)m, (void)h;
    return MODEL_OK;
}

int model_clock(ModelData *m, int clock) {
    if (clock == CLOCK_beat) {
        m->beats += 1;
        m->t_beat = m->time;
        if (m->period != m->period_now) { /* the tunable period changed: the new one from this beat on */
            m->period_now = m->period;
            fmu_set_interval(m, CLOCK_beat, m->period);
        }
    } else if (clock == CLOCK_chirp) {
        m->chirps += 1;
        m->t_chirp = m->time;
        fmu_set_interval(m, CLOCK_chirp, 0.01 * (1 + m->chirps % 3));
        if (m->chirps % 3 == 0) fmu_set_interval(m, CLOCK_alarm, m->delay);
    } else if (clock == CLOCK_alarm) {
        m->alarms += 1;
        m->t_alarm = m->time;
    }
    return MODEL_OK;
}
