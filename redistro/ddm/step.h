/* A ddm's admission and emission (ddm/step_kernel.c), for the CompiledAnswer. */
#ifndef REDISTRO_STEP_H
#define REDISTRO_STEP_H

#include "wire.h"

/* The arguments of ddm_admit's and ddm_emit's plans, in their signatures' order. */
enum { DA_LD, DA_CODEC, DA_PARAMS, DA_ROWS, DA_SRC, DA_EX, DA_LAT, DA_STATE };
enum { DE_LD, DE_CODEC, DE_PARAMS, DE_ROWS, DE_OUT, DE_WIRE, DE_EX };

/* The plans of ddm_admit and ddm_emit are sound (else an error is set, 0). */
int step_plans_ok(PlanObject *admit, PlanObject *emit);
/* ddm_admit's common case: the robot that took the record, -1 none, -2 an error. */
long step_admit(PlanObject *admit, const uint8_t *raw, Py_ssize_t len);
/* ddm_emit: the robots' mask, -1 a torn read, -2 an error; *wsize a record's bytes. */
long step_emit(PlanObject *emit, Py_ssize_t *wsize);

#endif
