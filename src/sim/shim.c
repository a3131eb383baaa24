/*
 * Error escape for MuJoCo 2.2 (compiled by build.rs with the `cc` crate).
 *
 * MuJoCo assumes `mju_error` never returns: after it, `mju_malloc` hands back
 * NULL and `mj_stackAlloc` hands back memory past the end of the stack, and the
 * caller carries on. The official Python bindings leave MuJoCo through the error
 * handler; C cannot throw, so each guarded entry point below runs its MuJoCo call
 * after `setjmp`, and the handler `longjmp`s back into it. Only C frames (ours
 * and MuJoCo's engine, which is C) lie between the two: no Rust frame is ever
 * skipped. The guarded function then returns 1 and the message stays readable
 * through `rall_last_error` on the same thread.
 *
 * MuJoCo 2.2's handler is one global (`mju_user_error`); the jump target is per
 * thread, so envs stepping on several threads each return to their own call.
 * An error raised on a thread with no guarded call in progress cannot be
 * returned from safely: the handler then aborts (MuJoCo's own default is exit).
 */
#include <setjmp.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include <mujoco/mujoco.h>

#define RALL_MSG_LEN 1024

static _Thread_local jmp_buf* rall_jump = NULL;
static _Thread_local char rall_message[RALL_MSG_LEN];

static void rall_error_handler(const char* msg) {
  if (msg) {
    strncpy(rall_message, msg, RALL_MSG_LEN - 1);
    rall_message[RALL_MSG_LEN - 1] = '\0';
  } else {
    strcpy(rall_message, "(no message)");
  }
  if (rall_jump) {
    longjmp(*rall_jump, 1);
  }
  fprintf(stderr, "rall: MuJoCo error outside a guarded call, aborting: %s\n", rall_message);
  abort();
}

void rall_install_error_handler(void) { mju_user_error = rall_error_handler; }

const char* rall_last_error(void) { return rall_message; }

/* Runs CALL with the jump target set; 0 on success, 1 when MuJoCo raised an
 * error (the target of the enclosing guarded call, if any, is restored). */
#define RALL_GUARD(CALL)             \
  do {                               \
    jmp_buf here;                    \
    jmp_buf* outer = rall_jump;      \
    rall_message[0] = '\0';          \
    if (setjmp(here) != 0) {         \
      rall_jump = outer;             \
      return 1;                      \
    }                                \
    rall_jump = &here;               \
    CALL;                            \
    rall_jump = outer;               \
    return 0;                        \
  } while (0)

int rall_mj_loadXML(const char* filename, const mjVFS* vfs, char* error, int error_sz,
                    mjModel** out) {
  *out = NULL;
  RALL_GUARD(*out = mj_loadXML(filename, vfs, error, error_sz));
}

int rall_mj_copyModel(const mjModel* src, mjModel** out) {
  *out = NULL;
  RALL_GUARD(*out = mj_copyModel(NULL, src));
}

int rall_mj_makeData(const mjModel* m, mjData** out) {
  *out = NULL;
  RALL_GUARD(*out = mj_makeData(m));
}

int rall_mj_step(const mjModel* m, mjData* d) { RALL_GUARD(mj_step(m, d)); }

int rall_mj_forward(const mjModel* m, mjData* d) { RALL_GUARD(mj_forward(m, d)); }

int rall_mj_resetData(const mjModel* m, mjData* d) { RALL_GUARD(mj_resetData(m, d)); }

int rall_mj_resetDataKeyframe(const mjModel* m, mjData* d, int key) {
  RALL_GUARD(mj_resetDataKeyframe(m, d, key));
}

int rall_mj_contactForce(const mjModel* m, const mjData* d, int id, mjtNum* result) {
  RALL_GUARD(mj_contactForce(m, d, id, result));
}
