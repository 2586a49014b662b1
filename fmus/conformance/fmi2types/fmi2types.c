/* fmi2types: each output echoes its input (see fmu.yaml). */
#include <stdio.h>

#include "fmu_model.h"

static void outputs(ModelData *m) {
    m->x_out = m->x_in;
    m->n_out = m->n_in;
    m->flag_out = m->flag_in;
    m->mode_out = m->mode_in;
    m->mode_param_out = m->mode;
    snprintf(m->text_out, sizeof m->text_out, "%s:%s", m->label, m->text_in);
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
