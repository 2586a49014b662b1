/* moving_floor: x = e A sin(phi), phi' = 2 pi f, and the envelope e ramps linearly to 1 (enabled)
 * or 0 (disabled) in `ramp` seconds, so switching never jerks the floor. It starts at 0: a floor
 * added to a running world eases in (as its Python twin, dynabrain.modules.floor, does). The tracking force is
 * kp (x - q) + kd (v - qd) + mass * a, with v and a the exact derivatives of x. */
#include <math.h>

#include "fmu_model.h"

static const double TWO_PI = 6.283185307179586;

static void reference(ModelData *m, double de) {
    double w = TWO_PI * m->frequency, s = sin(m->phase), c = cos(m->phase);
    double A = m->amplitude, e = m->envelope;
    m->position = e * A * s;
    m->velocity = de * A * s + e * A * w * c;
    double accel = 2.0 * de * A * w * c - e * A * w * w * s;
    m->force = m->kp * (m->position - m->q) + m->kd * (m->velocity - m->qd) + m->mass * accel;
}

static double envelope_rate(const ModelData *m) {
    double target = m->enabled ? 1.0 : 0.0;
    if (m->envelope == target) return 0.0;
    double rate = m->ramp > 0.0 ? 1.0 / m->ramp : INFINITY;
    return target > m->envelope ? rate : -rate;
}

int model_init(ModelData *m) {
    if (!(m->frequency >= 0.0) || !(m->ramp >= 0.0)) {
        fmu_log(m, MODEL_ERROR, "frequency (%g) and ramp (%g) must be >= 0", m->frequency, m->ramp);
        return MODEL_ERROR;
    }
    m->phase = TWO_PI * m->frequency * m->time;
    m->envelope = 0.0;
    reference(m, 0.0);
    return MODEL_OK;
}

int model_step(ModelData *m, double h) {
    double rate = envelope_rate(m);
    double e = m->envelope + rate * h;
    m->envelope = e > 1.0 ? 1.0 : e < 0.0 ? 0.0 : e;
    m->phase = fmod(m->phase + TWO_PI * m->frequency * h, TWO_PI);
    reference(m, envelope_rate(m) != 0.0 ? rate : 0.0);
    return MODEL_OK;
}
