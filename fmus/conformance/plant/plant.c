/* plant: y follows gain * u with time constant tau (exact for a step held constant). */
#include <math.h>

#include "fmu_model.h"

int model_init(ModelData *m) {
    (void)m;
    return MODEL_OK;
}

int model_step(ModelData *m, double h) {
    m->y += (1.0 - exp(-h / m->tau)) * (m->gain * m->u - m->y);
    return MODEL_OK;
}
