/* FMI 1.0 co-simulation API of a dynabrain C FMU, on the version-neutral core (fmu_glue.h).
 *
 * FMI 1.0 names every function after the model: `<modelIdentifier>_fmiDoStep`; the build passes
 * MODEL_IDENTIFIER. It has no FMU states (no get/set state): a master cannot roll it back. A
 * terminate request (fmu_stop) has no FMI 1.0 status of its own: the step that asks returns
 * fmiError with a message that says so. */
#include <stdlib.h>
#include <string.h>

#include "fmi1Functions.h"
#include "fmu_glue.h"

#ifndef MODEL_IDENTIFIER
#error "MODEL_IDENTIFIER must name the model (the build passes -DMODEL_IDENTIFIER=<name>)"
#endif

#define FMI1_PASTE(a, b) a##_##b
#define FMI1_NAME(a, b) FMI1_PASTE(a, b)
#define FMI1(f) FMI1_NAME(MODEL_IDENTIFIER, f)
#if defined(__GNUC__)
#define FMI1_EXPORT __attribute__((visibility("default")))
#else
#define FMI1_EXPORT
#endif
#define INST ((Instance *)c)

/* The master's callbacks, copied at instantiation (FMI 1.0 passes them by value). */
typedef struct {
    fmi1CallbackFunctions functions;
} Callbacks1;

static void emit1(Instance *inst, int status, const char *category, const char *message) {
    const Callbacks1 *cb = inst->env;
    char escaped[2048];
    size_t k = 0;
    if (!cb || !cb->functions.logger) return;
    for (const char *p = message; *p && k + 2 < sizeof escaped; ++p) { /* the logger takes a printf format */
        if (*p == '%') escaped[k++] = '%';
        escaped[k++] = *p;
    }
    escaped[k] = '\0';
    cb->functions.logger(inst, inst->name, (fmi1Status)status, category, escaped);
}

FMI1_EXPORT const char *FMI1(fmiGetTypesPlatform)(void) { return "standard32"; }
FMI1_EXPORT const char *FMI1(fmiGetVersion)(void) { return "1.0"; }

FMI1_EXPORT fmi1Status FMI1(fmiSetDebugLogging)(fmi1Component c, fmi1Boolean loggingOn) {
    if (!c) return fmi1Error;
    INST->logging = loggingOn != fmi1False;
    return fmi1OK;
}

FMI1_EXPORT fmi1Component FMI1(fmiInstantiateSlave)(fmi1String instanceName, fmi1String fmuGUID,
                                                    fmi1String fmuLocation, fmi1String mimeType, fmi1Real timeout,
                                                    fmi1Boolean visible, fmi1Boolean interactive,
                                                    fmi1CallbackFunctions functions, fmi1Boolean loggingOn) {
    (void)fmuLocation, (void)mimeType, (void)timeout, (void)visible, (void)interactive;
    Callbacks1 *cb = calloc(1, sizeof *cb);
    if (!cb) return NULL;
    cb->functions = functions;
    Instance *inst = core_new(instanceName, fmuGUID, emit1, cb, NULL, loggingOn != fmi1False);
    if (!inst) free(cb);
    return inst;
}

FMI1_EXPORT void FMI1(fmiFreeSlaveInstance)(fmi1Component c) {
    if (!c) return;
    void *cb = INST->env;
    core_free(INST);
    free(cb);
}

FMI1_EXPORT fmi1Status FMI1(fmiInitializeSlave)(fmi1Component c, fmi1Real tStart, fmi1Boolean stopTimeDefined,
                                                fmi1Real tStop) {
    (void)stopTimeDefined, (void)tStop;
    if (!c) return fmi1Error;
    int s = core_enter_init(INST, tStart);
    if (s > fmi1Warning) return (fmi1Status)s;
    int e = core_exit_init(INST);
    return (fmi1Status)(e > s ? e : s);
}

FMI1_EXPORT fmi1Status FMI1(fmiTerminateSlave)(fmi1Component c) { return (fmi1Status)core_terminate(INST); }

FMI1_EXPORT fmi1Status FMI1(fmiResetSlave)(fmi1Component c) {
    if (!c) return fmi1Error;
    if (INST->mode == MODE_FATAL) return fmi1Fatal;
    core_reset(INST);
    return fmi1OK;
}

FMI1_EXPORT fmi1Status FMI1(fmiGetReal)(fmi1Component c, const fmi1ValueReference vr[], size_t nvr,
                                        fmi1Real value[]) {
    return (fmi1Status)core_get(INST, W_F64, vr, nvr, value, NULL, nvr, "fmiGetReal");
}

FMI1_EXPORT fmi1Status FMI1(fmiGetInteger)(fmi1Component c, const fmi1ValueReference vr[], size_t nvr,
                                           fmi1Integer value[]) {
    return (fmi1Status)core_get(INST, W_I32, vr, nvr, value, NULL, nvr, "fmiGetInteger");
}

FMI1_EXPORT fmi1Status FMI1(fmiGetBoolean)(fmi1Component c, const fmi1ValueReference vr[], size_t nvr,
                                           fmi1Boolean value[]) {
    return (fmi1Status)core_get(INST, W_BOOL8, vr, nvr, value, NULL, nvr, "fmiGetBoolean");
}

FMI1_EXPORT fmi1Status FMI1(fmiGetString)(fmi1Component c, const fmi1ValueReference vr[], size_t nvr,
                                          fmi1String value[]) {
    return (fmi1Status)core_get(INST, W_STR, vr, nvr, (void *)value, NULL, nvr, "fmiGetString");
}

FMI1_EXPORT fmi1Status FMI1(fmiSetReal)(fmi1Component c, const fmi1ValueReference vr[], size_t nvr,
                                        const fmi1Real value[]) {
    return (fmi1Status)core_set(INST, W_F64, vr, nvr, value, NULL, nvr, "fmiSetReal");
}

FMI1_EXPORT fmi1Status FMI1(fmiSetInteger)(fmi1Component c, const fmi1ValueReference vr[], size_t nvr,
                                           const fmi1Integer value[]) {
    return (fmi1Status)core_set(INST, W_I32, vr, nvr, value, NULL, nvr, "fmiSetInteger");
}

FMI1_EXPORT fmi1Status FMI1(fmiSetBoolean)(fmi1Component c, const fmi1ValueReference vr[], size_t nvr,
                                           const fmi1Boolean value[]) {
    return (fmi1Status)core_set(INST, W_BOOL8, vr, nvr, value, NULL, nvr, "fmiSetBoolean");
}

FMI1_EXPORT fmi1Status FMI1(fmiSetString)(fmi1Component c, const fmi1ValueReference vr[], size_t nvr,
                                          const fmi1String value[]) {
    return (fmi1Status)core_set(INST, W_STR, vr, nvr, value, NULL, nvr, "fmiSetString");
}

FMI1_EXPORT fmi1Status FMI1(fmiSetRealInputDerivatives)(fmi1Component c, const fmi1ValueReference vr[], size_t nvr,
                                                        const fmi1Integer order[], const fmi1Real value[]) {
    (void)vr, (void)nvr, (void)order, (void)value;
    return (fmi1Status)core_unsupported(INST, "fmiSetRealInputDerivatives");
}

FMI1_EXPORT fmi1Status FMI1(fmiGetRealOutputDerivatives)(fmi1Component c, const fmi1ValueReference vr[], size_t nvr,
                                                         const fmi1Integer order[], fmi1Real value[]) {
    (void)vr, (void)nvr, (void)order, (void)value;
    return (fmi1Status)core_unsupported(INST, "fmiGetRealOutputDerivatives");
}

FMI1_EXPORT fmi1Status FMI1(fmiDoStep)(fmi1Component c, fmi1Real currentCommunicationPoint,
                                       fmi1Real communicationStepSize, fmi1Boolean newStep) {
    (void)newStep;
    int s = core_do_step(INST, currentCommunicationPoint, communicationStepSize);
    if (s <= fmi1Warning && INST->stop) {
        core_log(INST, fmi1Error, "logStatusError", "the model asked to end the simulation at t=%g s",
                 INST->d.time);
        return fmi1Error;
    }
    return (fmi1Status)s;
}

FMI1_EXPORT fmi1Status FMI1(fmiCancelStep)(fmi1Component c) {
    return (fmi1Status)core_unsupported(INST, "fmiCancelStep");
}

FMI1_EXPORT fmi1Status FMI1(fmiGetStatus)(fmi1Component c, const fmi1StatusKind s, fmi1Status *value) {
    if (!c || !value || s != fmi1DoStepStatus) return (fmi1Status)core_unsupported(INST, "fmiGetStatus");
    *value = fmi1OK; /* steps are synchronous */
    return fmi1OK;
}

FMI1_EXPORT fmi1Status FMI1(fmiGetRealStatus)(fmi1Component c, const fmi1StatusKind s, fmi1Real *value) {
    if (!c || !value || s != fmi1LastSuccessfulTime) return (fmi1Status)core_unsupported(INST, "fmiGetRealStatus");
    *value = INST->d.time;
    return fmi1OK;
}

FMI1_EXPORT fmi1Status FMI1(fmiGetIntegerStatus)(fmi1Component c, const fmi1StatusKind s, fmi1Integer *value) {
    (void)s, (void)value;
    return (fmi1Status)core_unsupported(INST, "fmiGetIntegerStatus");
}

FMI1_EXPORT fmi1Status FMI1(fmiGetBooleanStatus)(fmi1Component c, const fmi1StatusKind s, fmi1Boolean *value) {
    (void)s, (void)value;
    return (fmi1Status)core_unsupported(INST, "fmiGetBooleanStatus");
}

FMI1_EXPORT fmi1Status FMI1(fmiGetStringStatus)(fmi1Component c, const fmi1StatusKind s, fmi1String *value) {
    (void)s, (void)value;
    return (fmi1Status)core_unsupported(INST, "fmiGetStringStatus");
}
