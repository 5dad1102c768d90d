#include "fakecam.h"

#include <arv.h>
#include <errno.h>
#include <fcntl.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <sys/file.h>
#include <sys/prctl.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>
#include "drvtest.h"

static int lock_fd = -1;

pid_t fakecam_start(int lost) {
  if (lock_fd < 0) {
    lock_fd = open("/tmp/vlff-fake-gv-camera.lock", O_RDWR | O_CREAT | O_CLOEXEC, 0666);
    if (lock_fd < 0 || flock(lock_fd, LOCK_EX)) return -1;
  }
  pid_t parent = getpid();
  pid_t pid = fork();
  if (pid < 0) return -1;
  if (pid == 0) {
    prctl(PR_SET_PDEATHSIG, SIGKILL);
    if (getppid() != parent) _exit(1);
    int null = open("/dev/null", O_WRONLY);
    if (null >= 0) dup2(null, 1), dup2(null, 2);
    char r[16];
    snprintf(r, sizeof r, "%d", lost);
    if (lost > 0)
      execlp("arv-fake-gv-camera-0.8", "arv-fake-gv-camera-0.8", "-i", "127.0.0.1", "-r", r, (char *)NULL);
    else
      execlp("arv-fake-gv-camera-0.8", "arv-fake-gv-camera-0.8", "-i", "127.0.0.1", (char *)NULL);
    _exit(127);
  }
  /* Ready when a control connection succeeds. */
  for (int i = 0; i < 100; i++) {
    sleep_ms(50);
    int st;
    if (waitpid(pid, &st, WNOHANG) == pid) return -1;
    GError *e = NULL;
    ArvCamera *c = arv_camera_new("127.0.0.1", &e);
    g_clear_error(&e);
    if (c) {
      g_object_unref(c);
      return pid;
    }
  }
  fakecam_kill(pid);
  return -1;
}

void fakecam_kill(pid_t pid) {
  if (pid <= 0) return;
  kill(pid, SIGKILL);
  waitpid(pid, NULL, 0);
}

void fakecam_stop(pid_t pid) {
  fakecam_kill(pid);
  if (lock_fd >= 0) {
    close(lock_fd);
    lock_fd = -1;
  }
}
