/* nonfinite: root = sqrt(u), inverse = 1 / u, computed without checks. */
#include <math.h>

#include "fmu_model.h"

static void outputs(ModelData *m) {
    m->root = sqrt(m->u);
    m->inverse = 1.0 / m->u;
}

int model_init(ModelData *m) {
    outputs(m);
    return MODEL_OK;
}

int model_step(ModelData *m, double h) {
    (void)h;
    outputs(m);
    return MODEL_OK;
}
