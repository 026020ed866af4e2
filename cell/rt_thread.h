/* A native loop's thread, created at its real-time priority (cell/sched.py: the process's Python
 * stays at the normal policy, the loop is real-time from its first instruction). Included by
 * cell/robot/tick.c and cell/dataplane/native.c. */
#ifndef CELL_RT_THREAD_H
#define CELL_RT_THREAD_H

#include <errno.h>
#include <pthread.h>
#include <sched.h>

/* Start fn(arg) in `thread` at SCHED_FIFO `priority` (0, or refused: the caller's scheduling,
 * inherited); 0, or the errno of what failed */
static inline int rt_thread_start(pthread_t *thread, int priority, void *(*fn)(void *), void *arg)
{
    pthread_attr_t attr;
    pthread_attr_init(&attr);
    if (priority > 0) {
        struct sched_param sp = {.sched_priority = priority};
        pthread_attr_setinheritsched(&attr, PTHREAD_EXPLICIT_SCHED);
        pthread_attr_setschedpolicy(&attr, SCHED_FIFO);
        pthread_attr_setschedparam(&attr, &sp);
    }
    int rc = pthread_create(thread, &attr, fn, arg);
    if (rc == EPERM && priority > 0) { /* no real-time priority here: as the caller runs */
        pthread_attr_setinheritsched(&attr, PTHREAD_INHERIT_SCHED);
        rc = pthread_create(thread, &attr, fn, arg);
    }
    pthread_attr_destroy(&attr);
    return rc;
}

#endif
