/* affine: y = gain * u + offset, one channel, counting the steps it takes (a step taken again after a
   rollback is not counted twice: the count is state). */
#include "fmu_model.h"

static void outputs(ModelData *m) {
    m->y = m->gain * m->u + m->offset;
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
