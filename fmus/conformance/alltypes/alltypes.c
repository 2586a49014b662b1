/* alltypes: each output echoes its input (see fmu.yaml). */
#include <stdio.h>
#include <string.h>

#include "fmu_model.h"

static void outputs(ModelData *m) {
    m->f64_out = m->f64_in;
    m->f32_out = m->f32_in;
    m->i8_out = m->i8_in;
    m->u8_out = m->u8_in;
    m->i16_out = m->i16_in;
    m->u16_out = m->u16_in;
    m->i32_out = m->i32_in;
    m->u32_out = m->u32_in;
    m->i64_out = m->i64_in + m->offset;
    m->u64_out = m->u64_in;
    m->flag_out = m->flag_in;
    m->mode_out = m->mode_in;
    m->level_out = m->level;
    snprintf(m->text_out, sizeof m->text_out, "%s:%s", m->label, m->text_in);
    m->blob_out.size = m->key.size + m->blob_in.size;
    memcpy(m->blob_out.data, m->key.data, m->key.size);
    memcpy(m->blob_out.data + m->key.size, m->blob_in.data, m->blob_in.size);
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
