/* servo: tau_cmd = clamp(kp (q_ref - q) - kd qd, +-tau_max); the motor follows tau_cmd with a
 * first-order lag of time constant `lag` (integrated exactly over each step). */
#include <math.h>

#include "fmu_model.h"

static double clamp(double x, double limit) { return x > limit ? limit : x < -limit ? -limit : x; }

static int check(const ModelData *m) {
    if (!(m->tau_max >= 0.0) || !(m->lag >= 0.0)) {
        fmu_log(m, MODEL_ERROR, "tau_max (%g) and lag (%g) must be >= 0", m->tau_max, m->lag);
        return MODEL_ERROR;
    }
    return MODEL_OK;
}

static void command(ModelData *m) {
    for (int i = 0; i < N; ++i) m->tau_cmd[i] = clamp(m->kp * (m->q_ref[i] - m->q[i]) - m->kd * m->qd[i], m->tau_max);
}

int model_init(ModelData *m) {
    int s = check(m);
    if (s) return s;
    command(m);
    for (int i = 0; i < N; ++i) m->tau[i] = m->lag > 0.0 ? 0.0 : m->tau_cmd[i];
    return MODEL_OK;
}

int model_step(ModelData *m, double h) {
    int s = check(m);
    if (s) return s;
    command(m);
    double a = m->lag > 0.0 ? 1.0 - exp(-h / m->lag) : 1.0;
    for (int i = 0; i < N; ++i) m->tau[i] += a * (m->tau_cmd[i] - m->tau[i]);
    return MODEL_OK;
}
