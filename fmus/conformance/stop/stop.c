/* stop: counts its steps and outputs its time; asks to end the simulation at stop_at. */
#include "fmu_model.h"

int model_init(ModelData *m) {
    m->t = m->time;
    m->steps = 0;
    return MODEL_OK;
}

int model_step(ModelData *m, double h) {
    m->t = m->time + h;
    m->steps += 1;
    if (m->t >= m->stop_at - 1e-9) fmu_stop(m, "reached stop_at=%g s at t=%g s", m->stop_at, m->t);
    return MODEL_OK;
}
