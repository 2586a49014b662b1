/* FMI 2.0 co-simulation API of a dynabrain C FMU, on the version-neutral core (fmu_glue.h). */
#include <stdio.h>
#include <string.h>

#include "fmi2Functions.h"
#include "fmu_glue.h"

#define INST ((Instance *)c)

static void emit2(Instance *inst, int status, const char *category, const char *message) {
    const fmi2CallbackFunctions *cb = inst->env;
    char escaped[2048];
    size_t k = 0;
    if (!cb || !cb->logger) return;
    for (const char *p = message; *p && k + 2 < sizeof escaped; ++p) { /* the logger takes a printf format */
        if (*p == '%') escaped[k++] = '%';
        escaped[k++] = *p;
    }
    escaped[k] = '\0';
    cb->logger(cb->componentEnvironment, inst->name, (fmi2Status)status, category, escaped);
}

const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }
const char *fmi2GetVersion(void) { return fmi2Version; }

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean loggingOn, size_t nCategories,
                               const fmi2String categories[]) {
    (void)nCategories;
    (void)categories;
    if (!c) return fmi2Error;
    INST->logging = loggingOn != fmi2False;
    return fmi2OK;
}

fmi2Component fmi2Instantiate(fmi2String instanceName, fmi2Type fmuType, fmi2String fmuGUID,
                              fmi2String fmuResourceLocation, const fmi2CallbackFunctions *functions,
                              fmi2Boolean visible, fmi2Boolean loggingOn) {
    (void)fmuResourceLocation;
    (void)visible;
    if (fmuType != fmi2CoSimulation) {
        if (functions && functions->logger)
            functions->logger(functions->componentEnvironment, instanceName, fmi2Error, "logStatusError",
                              "this FMU supports co-simulation only");
        return NULL;
    }
    return core_new(instanceName, fmuGUID, emit2, (void *)functions, NULL, loggingOn != fmi2False);
}

void fmi2FreeInstance(fmi2Component c) { core_free(INST); }

fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean toleranceDefined, fmi2Real tolerance,
                               fmi2Real startTime, fmi2Boolean stopTimeDefined, fmi2Real stopTime) {
    (void)toleranceDefined;
    (void)tolerance;
    (void)stopTimeDefined;
    (void)stopTime;
    int s = core_usable(INST, "fmi2SetupExperiment");
    if (s) return (fmi2Status)s;
    INST->d.time = startTime;
    return fmi2OK;
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c) {
    if (!c) return fmi2Error;
    return (fmi2Status)core_enter_init(INST, INST->d.time);
}

fmi2Status fmi2ExitInitializationMode(fmi2Component c) { return (fmi2Status)core_exit_init(INST); }
fmi2Status fmi2Terminate(fmi2Component c) { return (fmi2Status)core_terminate(INST); }

fmi2Status fmi2Reset(fmi2Component c) {
    if (!c) return fmi2Error;
    if (INST->mode == MODE_FATAL) return fmi2Fatal;
    core_reset(INST);
    return fmi2OK;
}

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Real value[]) {
    return (fmi2Status)core_get(INST, W_F64, vr, nvr, value, NULL, nvr, "fmi2GetReal");
}

fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Integer value[]) {
    return (fmi2Status)core_get(INST, W_I32, vr, nvr, value, NULL, nvr, "fmi2GetInteger");
}

fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Boolean value[]) {
    return (fmi2Status)core_get(INST, W_BOOL_INT, vr, nvr, value, NULL, nvr, "fmi2GetBoolean");
}

fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2String value[]) {
    return (fmi2Status)core_get(INST, W_STR, vr, nvr, (void *)value, NULL, nvr, "fmi2GetString");
}

fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Real value[]) {
    return (fmi2Status)core_set(INST, W_F64, vr, nvr, value, NULL, nvr, "fmi2SetReal");
}

fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Integer value[]) {
    return (fmi2Status)core_set(INST, W_I32, vr, nvr, value, NULL, nvr, "fmi2SetInteger");
}

fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Boolean value[]) {
    return (fmi2Status)core_set(INST, W_BOOL_INT, vr, nvr, value, NULL, nvr, "fmi2SetBoolean");
}

fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2String value[]) {
    return (fmi2Status)core_set(INST, W_STR, vr, nvr, value, NULL, nvr, "fmi2SetString");
}

fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *FMUstate) {
    return (fmi2Status)core_get_state(INST, FMUstate);
}

fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate FMUstate) {
    return (fmi2Status)core_set_state(INST, FMUstate);
}

fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *FMUstate) {
    return (fmi2Status)core_free_state(INST, FMUstate);
}

fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate FMUstate, size_t *size) {
    (void)c;
    (void)FMUstate;
    if (!size) return fmi2Error;
    *size = core_serialized_size();
    return fmi2OK;
}

fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate FMUstate, fmi2Byte serializedState[], size_t size) {
    return (fmi2Status)core_serialize(INST, FMUstate, (unsigned char *)serializedState, size);
}

fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte serializedState[], size_t size,
                                   fmi2FMUstate *FMUstate) {
    return (fmi2Status)core_deserialize(INST, (const unsigned char *)serializedState, size, FMUstate);
}

fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference vUnknown_ref[], size_t nUnknown,
                                        const fmi2ValueReference vKnown_ref[], size_t nKnown,
                                        const fmi2Real dvKnown[], fmi2Real dvUnknown[]) {
    (void)vUnknown_ref, (void)nUnknown, (void)vKnown_ref, (void)nKnown, (void)dvKnown, (void)dvUnknown;
    return (fmi2Status)core_unsupported(INST, "fmi2GetDirectionalDerivative");
}

fmi2Status fmi2SetRealInputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                       const fmi2Integer order[], const fmi2Real value[]) {
    (void)vr, (void)nvr, (void)order, (void)value;
    return (fmi2Status)core_unsupported(INST, "fmi2SetRealInputDerivatives");
}

fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                        const fmi2Integer order[], fmi2Real value[]) {
    (void)vr, (void)nvr, (void)order, (void)value;
    return (fmi2Status)core_unsupported(INST, "fmi2GetRealOutputDerivatives");
}

fmi2Status fmi2DoStep(fmi2Component c, fmi2Real currentCommunicationPoint, fmi2Real communicationStepSize,
                      fmi2Boolean noSetFMUStatePriorToCurrentPoint) {
    (void)noSetFMUStatePriorToCurrentPoint;
    int s = core_do_step(INST, currentCommunicationPoint, communicationStepSize);
    /* FMI 2.0 asks to end the simulation with fmi2Discard; fmi2GetBooleanStatus(fmi2Terminated) says why */
    if (s <= fmi2Warning && INST->stop) return fmi2Discard;
    return (fmi2Status)s;
}

fmi2Status fmi2CancelStep(fmi2Component c) { return (fmi2Status)core_unsupported(INST, "fmi2CancelStep"); }

fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s, fmi2Status *value) {
    (void)s, (void)value;
    return (fmi2Status)core_unsupported(INST, "fmi2GetStatus");
}

fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *value) {
    if (!c || !value || s != fmi2LastSuccessfulTime) return (fmi2Status)core_unsupported(INST, "fmi2GetRealStatus");
    *value = INST->d.time;
    return fmi2OK;
}

fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind s, fmi2Integer *value) {
    (void)s, (void)value;
    return (fmi2Status)core_unsupported(INST, "fmi2GetIntegerStatus");
}

fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind s, fmi2Boolean *value) {
    if (!c || !value || s != fmi2Terminated) return (fmi2Status)core_unsupported(INST, "fmi2GetBooleanStatus");
    *value = INST->stop ? fmi2True : fmi2False;
    return fmi2OK;
}

fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind s, fmi2String *value) {
    (void)s, (void)value;
    return (fmi2Status)core_unsupported(INST, "fmi2GetStringStatus");
}
