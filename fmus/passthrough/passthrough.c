/* passthrough: y = gain * u on N channels, counting the steps it takes. */
#include "fmu_model.h"

static void outputs(ModelData *m) {
    for (int i = 0; i < N; ++i) m->y[i] = m->gain * m->u[i];
}

int model_init(ModelData *m) {
    m->steps = 0;
    outputs(m);
    return MODEL_OK;
}

int model_step(ModelData *m, double h) {
    (void)h;
    outputs(m);
    m->steps += 1;
    return MODEL_OK;
}
