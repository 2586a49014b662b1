/* FMI 3.0 co-simulation API of a dynabrain C FMU, on the version-neutral core (fmu_glue.h), with
 * event mode and clocks (time-based and triggered input clocks, output clocks). Model exchange and
 * scheduled execution are refused with fmi3Error and a log message, so every function of the
 * standard is present in the binary. */
#include <string.h>

#include "fmi3Functions.h"
#include "fmu_glue.h"

#define INST ((Instance *)instance)
#define UNSUPPORTED(call) return (fmi3Status)core_unsupported(INST, call)

static void emit3(Instance *inst, int status, const char *category, const char *message) {
    fmi3LogMessageCallback log = (fmi3LogMessageCallback)inst->logger;
    if (log) log(inst->env, (fmi3Status)status, category, message);
}

const char *fmi3GetVersion(void) { return fmi3Version; }

fmi3Status fmi3SetDebugLogging(fmi3Instance instance, fmi3Boolean loggingOn, size_t nCategories,
                               const fmi3String categories[]) {
    (void)nCategories, (void)categories;
    if (!instance) return fmi3Error;
    INST->logging = loggingOn;
    return fmi3OK;
}

fmi3Instance fmi3InstantiateModelExchange(fmi3String instanceName, fmi3String instantiationToken,
                                          fmi3String resourcePath, fmi3Boolean visible, fmi3Boolean loggingOn,
                                          fmi3InstanceEnvironment instanceEnvironment,
                                          fmi3LogMessageCallback logMessage) {
    (void)instanceName, (void)instantiationToken, (void)resourcePath, (void)visible, (void)loggingOn;
    if (logMessage) logMessage(instanceEnvironment, fmi3Error, "logStatusError", "this FMU supports co-simulation only");
    return NULL;
}

fmi3Instance fmi3InstantiateCoSimulation(fmi3String instanceName, fmi3String instantiationToken,
                                         fmi3String resourcePath, fmi3Boolean visible, fmi3Boolean loggingOn,
                                         fmi3Boolean eventModeUsed, fmi3Boolean earlyReturnAllowed,
                                         const fmi3ValueReference requiredIntermediateVariables[],
                                         size_t nRequiredIntermediateVariables,
                                         fmi3InstanceEnvironment instanceEnvironment,
                                         fmi3LogMessageCallback logMessage,
                                         fmi3IntermediateUpdateCallback intermediateUpdate) {
    (void)resourcePath, (void)visible;
    (void)requiredIntermediateVariables, (void)nRequiredIntermediateVariables, (void)intermediateUpdate;
    Instance *inst = core_new(instanceName, instantiationToken, emit3, instanceEnvironment, (void *)logMessage,
                              loggingOn);
    if (inst) inst->event_mode_used = eventModeUsed;
    if (inst) inst->early_allowed = earlyReturnAllowed;
    return inst;
}

fmi3Instance fmi3InstantiateScheduledExecution(fmi3String instanceName, fmi3String instantiationToken,
                                               fmi3String resourcePath, fmi3Boolean visible, fmi3Boolean loggingOn,
                                               fmi3InstanceEnvironment instanceEnvironment,
                                               fmi3LogMessageCallback logMessage,
                                               fmi3ClockUpdateCallback clockUpdate,
                                               fmi3LockPreemptionCallback lockPreemption,
                                               fmi3UnlockPreemptionCallback unlockPreemption) {
    (void)resourcePath, (void)visible, (void)lockPreemption, (void)unlockPreemption; /* no preemption here */
    Instance *inst = core_new(instanceName, instantiationToken, emit3, instanceEnvironment, (void *)logMessage,
                              loggingOn);
    if (inst) {
        inst->event_mode_used = true; /* initialization ends in clock activation mode (the event mode here) */
        inst->clock_update = (void *)clockUpdate;
    }
    return inst;
}

void fmi3FreeInstance(fmi3Instance instance) { core_free(INST); }

fmi3Status fmi3EnterInitializationMode(fmi3Instance instance, fmi3Boolean toleranceDefined, fmi3Float64 tolerance,
                                       fmi3Float64 startTime, fmi3Boolean stopTimeDefined, fmi3Float64 stopTime) {
    (void)toleranceDefined, (void)tolerance, (void)stopTimeDefined, (void)stopTime;
    return (fmi3Status)core_enter_init(INST, startTime);
}

fmi3Status fmi3ExitInitializationMode(fmi3Instance instance) { return (fmi3Status)core_exit_init(INST); }
fmi3Status fmi3EnterEventMode(fmi3Instance instance) { return (fmi3Status)core_enter_event_mode(INST); }
fmi3Status fmi3Terminate(fmi3Instance instance) { return (fmi3Status)core_terminate(INST); }

fmi3Status fmi3Reset(fmi3Instance instance) {
    if (!instance) return fmi3Error;
    if (INST->mode == MODE_FATAL) return fmi3Fatal;
    core_reset(INST);
    return fmi3OK;
}

/* Get and set of every type but clocks: the core checks the value references against the types. */
#define ACCESS(type, ctype, wire)                                                                               \
    fmi3Status fmi3Get##type(fmi3Instance instance, const fmi3ValueReference valueReferences[],                 \
                             size_t nValueReferences, ctype values[], size_t nValues) {                        \
        return (fmi3Status)core_get(INST, wire, valueReferences, nValueReferences, (void *)values, NULL, nValues, \
                                    "fmi3Get" #type);                                                          \
    }                                                                                                          \
    fmi3Status fmi3Set##type(fmi3Instance instance, const fmi3ValueReference valueReferences[],                 \
                             size_t nValueReferences, const ctype values[], size_t nValues) {                  \
        return (fmi3Status)core_set(INST, wire, valueReferences, nValueReferences, values, NULL, nValues,       \
                                    "fmi3Set" #type);                                                          \
    }

ACCESS(Float64, fmi3Float64, W_F64)
ACCESS(Float32, fmi3Float32, W_F32)
ACCESS(Int8, fmi3Int8, W_I8)
ACCESS(UInt8, fmi3UInt8, W_U8)
ACCESS(Int16, fmi3Int16, W_I16)
ACCESS(UInt16, fmi3UInt16, W_U16)
ACCESS(Int32, fmi3Int32, W_I32)
ACCESS(UInt32, fmi3UInt32, W_U32)
ACCESS(Int64, fmi3Int64, W_I64)
ACCESS(UInt64, fmi3UInt64, W_U64)
ACCESS(Boolean, fmi3Boolean, W_BOOL8)
ACCESS(String, fmi3String, W_STR)

fmi3Status fmi3GetBinary(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences,
                         size_t valueSizes[], fmi3Binary values[], size_t nValues) {
    return (fmi3Status)core_get(INST, W_BIN, valueReferences, nValueReferences, (void *)values, valueSizes, nValues,
                                "fmi3GetBinary");
}

fmi3Status fmi3SetBinary(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences,
                         const size_t valueSizes[], const fmi3Binary values[], size_t nValues) {
    return (fmi3Status)core_set(INST, W_BIN, valueReferences, nValueReferences, values, valueSizes, nValues,
                                "fmi3SetBinary");
}

fmi3Status fmi3GetClock(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences,
                        fmi3Clock values[]) {
    return (fmi3Status)core_get_clock(INST, valueReferences, nValueReferences, values);
}

fmi3Status fmi3SetClock(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences,
                        const fmi3Clock values[]) {
    return (fmi3Status)core_set_clock(INST, valueReferences, nValueReferences, values);
}

fmi3Status fmi3GetNumberOfVariableDependencies(fmi3Instance instance, fmi3ValueReference valueReference,
                                               size_t *nDependencies) {
    (void)valueReference, (void)nDependencies;
    UNSUPPORTED("fmi3GetNumberOfVariableDependencies");
}

fmi3Status fmi3GetVariableDependencies(fmi3Instance instance, fmi3ValueReference dependent,
                                       size_t elementIndicesOfDependent[], fmi3ValueReference independents[],
                                       size_t elementIndicesOfIndependents[], fmi3DependencyKind dependencyKinds[],
                                       size_t nDependencies) {
    (void)dependent, (void)elementIndicesOfDependent, (void)independents, (void)elementIndicesOfIndependents;
    (void)dependencyKinds, (void)nDependencies;
    UNSUPPORTED("fmi3GetVariableDependencies");
}

fmi3Status fmi3GetFMUState(fmi3Instance instance, fmi3FMUState *FMUState) {
    return (fmi3Status)core_get_state(INST, FMUState);
}

fmi3Status fmi3SetFMUState(fmi3Instance instance, fmi3FMUState FMUState) {
    return (fmi3Status)core_set_state(INST, FMUState);
}

fmi3Status fmi3FreeFMUState(fmi3Instance instance, fmi3FMUState *FMUState) {
    return (fmi3Status)core_free_state(INST, FMUState);
}

fmi3Status fmi3SerializedFMUStateSize(fmi3Instance instance, fmi3FMUState FMUState, size_t *size) {
    (void)instance, (void)FMUState;
    if (!size) return fmi3Error;
    *size = core_serialized_size();
    return fmi3OK;
}

fmi3Status fmi3SerializeFMUState(fmi3Instance instance, fmi3FMUState FMUState, fmi3Byte serializedState[],
                                 size_t size) {
    return (fmi3Status)core_serialize(INST, FMUState, serializedState, size);
}

fmi3Status fmi3DeserializeFMUState(fmi3Instance instance, const fmi3Byte serializedState[], size_t size,
                                   fmi3FMUState *FMUState) {
    return (fmi3Status)core_deserialize(INST, serializedState, size, FMUState);
}

fmi3Status fmi3GetDirectionalDerivative(fmi3Instance instance, const fmi3ValueReference unknowns[], size_t nUnknowns,
                                        const fmi3ValueReference knowns[], size_t nKnowns, const fmi3Float64 seed[],
                                        size_t nSeed, fmi3Float64 sensitivity[], size_t nSensitivity) {
    (void)unknowns, (void)nUnknowns, (void)knowns, (void)nKnowns, (void)seed, (void)nSeed;
    (void)sensitivity, (void)nSensitivity;
    UNSUPPORTED("fmi3GetDirectionalDerivative");
}

fmi3Status fmi3GetAdjointDerivative(fmi3Instance instance, const fmi3ValueReference unknowns[], size_t nUnknowns,
                                    const fmi3ValueReference knowns[], size_t nKnowns, const fmi3Float64 seed[],
                                    size_t nSeed, fmi3Float64 sensitivity[], size_t nSensitivity) {
    (void)unknowns, (void)nUnknowns, (void)knowns, (void)nKnowns, (void)seed, (void)nSeed;
    (void)sensitivity, (void)nSensitivity;
    UNSUPPORTED("fmi3GetAdjointDerivative");
}

fmi3Status fmi3EnterConfigurationMode(fmi3Instance instance) { UNSUPPORTED("fmi3EnterConfigurationMode"); }
fmi3Status fmi3ExitConfigurationMode(fmi3Instance instance) { UNSUPPORTED("fmi3ExitConfigurationMode"); }

fmi3Status fmi3GetIntervalDecimal(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                                  size_t nValueReferences, fmi3Float64 intervals[],
                                  fmi3IntervalQualifier qualifiers[]) {
    int q[64];
    if (nValueReferences > 64) UNSUPPORTED("fmi3GetIntervalDecimal of more than 64 clocks at once");
    int s = core_get_interval(INST, valueReferences, nValueReferences, intervals, q);
    for (size_t i = 0; s <= fmi3Warning && i < nValueReferences; ++i) qualifiers[i] = (fmi3IntervalQualifier)q[i];
    return (fmi3Status)s;
}

fmi3Status fmi3GetIntervalFraction(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                                   size_t nValueReferences, fmi3UInt64 counters[], fmi3UInt64 resolutions[],
                                   fmi3IntervalQualifier qualifiers[]) {
    (void)valueReferences, (void)nValueReferences, (void)counters, (void)resolutions, (void)qualifiers;
    UNSUPPORTED("fmi3GetIntervalFraction");
}

fmi3Status fmi3GetShiftDecimal(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                               size_t nValueReferences, fmi3Float64 shifts[]) {
    return (fmi3Status)core_get_shift(INST, valueReferences, nValueReferences, shifts);
}

fmi3Status fmi3GetShiftFraction(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                                size_t nValueReferences, fmi3UInt64 counters[], fmi3UInt64 resolutions[]) {
    (void)valueReferences, (void)nValueReferences, (void)counters, (void)resolutions;
    UNSUPPORTED("fmi3GetShiftFraction");
}

fmi3Status fmi3SetIntervalDecimal(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                                  size_t nValueReferences, const fmi3Float64 intervals[]) {
    (void)valueReferences, (void)nValueReferences, (void)intervals;
    UNSUPPORTED("fmi3SetIntervalDecimal");
}

fmi3Status fmi3SetIntervalFraction(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                                   size_t nValueReferences, const fmi3UInt64 counters[],
                                   const fmi3UInt64 resolutions[]) {
    (void)valueReferences, (void)nValueReferences, (void)counters, (void)resolutions;
    UNSUPPORTED("fmi3SetIntervalFraction");
}

fmi3Status fmi3SetShiftDecimal(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                               size_t nValueReferences, const fmi3Float64 shifts[]) {
    (void)valueReferences, (void)nValueReferences, (void)shifts;
    UNSUPPORTED("fmi3SetShiftDecimal");
}

fmi3Status fmi3SetShiftFraction(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                                size_t nValueReferences, const fmi3UInt64 counters[], const fmi3UInt64 resolutions[]) {
    (void)valueReferences, (void)nValueReferences, (void)counters, (void)resolutions;
    UNSUPPORTED("fmi3SetShiftFraction");
}

fmi3Status fmi3EvaluateDiscreteStates(fmi3Instance instance) { UNSUPPORTED("fmi3EvaluateDiscreteStates"); }

fmi3Status fmi3UpdateDiscreteStates(fmi3Instance instance, fmi3Boolean *discreteStatesNeedUpdate,
                                    fmi3Boolean *terminateSimulation, fmi3Boolean *nominalsOfContinuousStatesChanged,
                                    fmi3Boolean *valuesOfContinuousStatesChanged, fmi3Boolean *nextEventTimeDefined,
                                    fmi3Float64 *nextEventTime) {
    bool terminate = false;
    int s = core_update_discrete_states(INST, &terminate);
    if (discreteStatesNeedUpdate) *discreteStatesNeedUpdate = false; /* model_clock runs once per tick */
    if (terminateSimulation) *terminateSimulation = terminate;
    if (nominalsOfContinuousStatesChanged) *nominalsOfContinuousStatesChanged = false;
    if (valuesOfContinuousStatesChanged) *valuesOfContinuousStatesChanged = false;
    if (nextEventTimeDefined) *nextEventTimeDefined = false; /* time-based clocks say when they tick */
    if (nextEventTime) *nextEventTime = 0.0;
    return (fmi3Status)s;
}

fmi3Status fmi3EnterContinuousTimeMode(fmi3Instance instance) { UNSUPPORTED("fmi3EnterContinuousTimeMode"); }

fmi3Status fmi3CompletedIntegratorStep(fmi3Instance instance, fmi3Boolean noSetFMUStatePriorToCurrentPoint,
                                       fmi3Boolean *enterEventMode, fmi3Boolean *terminateSimulation) {
    (void)noSetFMUStatePriorToCurrentPoint, (void)enterEventMode, (void)terminateSimulation;
    UNSUPPORTED("fmi3CompletedIntegratorStep");
}

fmi3Status fmi3SetTime(fmi3Instance instance, fmi3Float64 time) {
    (void)time;
    UNSUPPORTED("fmi3SetTime");
}

fmi3Status fmi3SetContinuousStates(fmi3Instance instance, const fmi3Float64 continuousStates[],
                                   size_t nContinuousStates) {
    (void)continuousStates, (void)nContinuousStates;
    UNSUPPORTED("fmi3SetContinuousStates");
}

fmi3Status fmi3GetContinuousStateDerivatives(fmi3Instance instance, fmi3Float64 derivatives[],
                                             size_t nContinuousStates) {
    (void)derivatives, (void)nContinuousStates;
    UNSUPPORTED("fmi3GetContinuousStateDerivatives");
}

fmi3Status fmi3GetEventIndicators(fmi3Instance instance, fmi3Float64 eventIndicators[], size_t nEventIndicators) {
    (void)eventIndicators, (void)nEventIndicators;
    UNSUPPORTED("fmi3GetEventIndicators");
}

fmi3Status fmi3GetContinuousStates(fmi3Instance instance, fmi3Float64 continuousStates[], size_t nContinuousStates) {
    (void)continuousStates, (void)nContinuousStates;
    UNSUPPORTED("fmi3GetContinuousStates");
}

fmi3Status fmi3GetNominalsOfContinuousStates(fmi3Instance instance, fmi3Float64 nominals[],
                                             size_t nContinuousStates) {
    (void)nominals, (void)nContinuousStates;
    UNSUPPORTED("fmi3GetNominalsOfContinuousStates");
}

fmi3Status fmi3GetNumberOfEventIndicators(fmi3Instance instance, size_t *nEventIndicators) {
    if (!instance || !nEventIndicators) return fmi3Error;
    *nEventIndicators = 0;
    return fmi3OK;
}

fmi3Status fmi3GetNumberOfContinuousStates(fmi3Instance instance, size_t *nContinuousStates) {
    if (!instance || !nContinuousStates) return fmi3Error;
    *nContinuousStates = 0;
    return fmi3OK;
}

fmi3Status fmi3EnterStepMode(fmi3Instance instance) { return (fmi3Status)core_enter_step_mode(INST); }

fmi3Status fmi3GetOutputDerivatives(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                                    size_t nValueReferences, const fmi3Int32 orders[], fmi3Float64 values[],
                                    size_t nValues) {
    (void)valueReferences, (void)nValueReferences, (void)orders, (void)values, (void)nValues;
    UNSUPPORTED("fmi3GetOutputDerivatives");
}

fmi3Status fmi3DoStep(fmi3Instance instance, fmi3Float64 currentCommunicationPoint,
                      fmi3Float64 communicationStepSize, fmi3Boolean noSetFMUStatePriorToCurrentPoint,
                      fmi3Boolean *eventHandlingNeeded, fmi3Boolean *terminateSimulation, fmi3Boolean *earlyReturn,
                      fmi3Float64 *lastSuccessfulTime) {
    (void)noSetFMUStatePriorToCurrentPoint;
    int s = core_do_step(INST, currentCommunicationPoint, communicationStepSize);
    if (eventHandlingNeeded) *eventHandlingNeeded = instance && INST->event_mode_used && core_event_pending(INST);
    if (terminateSimulation) *terminateSimulation = instance && INST->stop;
    if (earlyReturn) *earlyReturn = instance && INST->early;
    if (lastSuccessfulTime && instance) *lastSuccessfulTime = INST->d.time;
    return (fmi3Status)s;
}

/* Scheduled execution: the partition of an input clock runs at once (model_clock), at its activation
 * time; an output clock it ticks is said with the clock update callback. */
fmi3Status fmi3ActivateModelPartition(fmi3Instance instance, fmi3ValueReference clockReference,
                                      fmi3Float64 activationTime) {
    Instance *inst = instance;
    if (!inst) return fmi3Error;
    if (!inst->clock_update) return (fmi3Status)core_unsupported(inst, "fmi3ActivateModelPartition");
    inst->d.time = activationTime;
    int s = core_activate(inst, clockReference);
    if (s > fmi3Warning) return (fmi3Status)s;
    if (core_event_pending(inst)) ((fmi3ClockUpdateCallback)inst->clock_update)(inst->env);
    return (fmi3Status)s;
}
