/* nostate: y integrates u; large inputs make a step fail (see fmu.yaml). */
#include "fmu_model.h"

int model_init(ModelData *m) {
    m->y = m->x;
    return MODEL_OK;
}

int model_step(ModelData *m, double h) {
    if (m->u > 3) { fmu_log(m, MODEL_FATAL, "u=%g broke the model", m->u); return MODEL_FATAL; }
    if (m->u > 2) { fmu_log(m, MODEL_ERROR, "u=%g is out of range", m->u); return MODEL_ERROR; }
    if (m->u > 1) { fmu_log(m, MODEL_DISCARD, "u=%g needs a smaller step", m->u); return MODEL_DISCARD; }
    m->x += m->u * h;
    m->y = m->x;
    return MODEL_OK;
}
