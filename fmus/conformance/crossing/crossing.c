/* crossing: a triangle wave that returns early at each turn (see fmu.yaml). */
#include "fmu_model.h"

int model_init(ModelData *m) {
    m->x = 0.0;
    m->up = 1;
    m->pieces = m->turns = 0;
    m->since = m->time;
    m->t_turn = -1.0;
    return MODEL_OK;
}

int model_step(ModelData *m, double h) {
    double t = m->time, end = m->time + h;
    m->pieces += 1;
    m->since = t;
    while (t < end) {
        double target = m->up ? m->high : 0.0;
        double at = t + (m->up ? target - m->x : m->x - target) / m->rate; /* when x reaches the target */
        if (at > end) {
            m->x += (m->up ? 1.0 : -1.0) * m->rate * (end - t);
            break;
        }
        m->x = target; /* a turn inside the step */
        m->up = !m->up;
        m->turns += 1;
        m->t_turn = at;
        fmu_tick(m, CLOCK_turn);
        if (fmu_return_early(m, at)) return MODEL_OK;
        t = at;
    }
    return MODEL_OK;
}
