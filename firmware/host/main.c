/* Host (POSIX) board: the valve controller core as a process on a pty (PROTOCOL.md 9).
 *
 *   valvectl [--clock real|virtual] [--speed F] [--pty-file PATH] [--pulse-log PATH]
 *            [--watchdog-ms MS]
 *
 * Prints "PTY <path>" and "PID <pid>" on stdout. Real clock: ticks of 2 ms / F from
 * CLOCK_MONOTONIC while a tick has work (playing, a trigger latched), else it sleeps until
 * a frame, the trigger or 20 ms; virtual clock: while playing, ticks as fast as possible but never ahead
 * of the program bytes (deterministic pulse ticks, no underrun); otherwise time stands
 * still. Trigger: the TRIGGER command or SIGUSR1. SIGTERM / SIGINT: valves off, exit 0.
 * The watchdog is emulated: the main loop feeds it every pass; STALL stops that. */
#define _XOPEN_SOURCE 700
#define _DEFAULT_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/select.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include "../core/board.h"
#include "../core/valvectl.h"

static vc_core core;
static int master = -1;
static FILE *plog;
static int virtual_clock;
static double speed = 1.0;
static uint64_t ctrl_us;                 /* controller time, us (tick clock) */
static uint64_t off_us[VC_N_VALVES];     /* valve v open while ctrl_us < off_us[v] */
static uint32_t stall_ms;
static uint8_t txbuf[1 << 20];
static size_t txlen;
static unsigned long tx_dropped;
static volatile sig_atomic_t got_trigger, got_stop;

/* ------------------------------------------------------------------ board.h */

void board_tx(const uint8_t *data, unsigned n)
{
    if (txlen + n > sizeof txbuf) { tx_dropped++; return; }
    memcpy(txbuf + txlen, data, n);
    txlen += n;
}

void board_valve_pulse(unsigned valve, uint16_t width_us, uint32_t play_tick)
{
    uint64_t end = ctrl_us + width_us;
    if (valve >= VC_N_VALVES) return;
    if (end > off_us[valve]) off_us[valve] = end;
    if (plog) fprintf(plog, "pulse %u %u %lu %u\n", (unsigned)core.plays, valve,
                      (unsigned long)play_tick, (unsigned)width_us);
}

void board_valves_off(void)
{
    unsigned v;
    for (v = 0; v < VC_N_VALVES; v++) off_us[v] = 0;
}

uint8_t board_outputs(void)
{
    uint8_t m = 0;
    unsigned v;
    for (v = 0; v < VC_N_VALVES; v++)
        if (ctrl_us < off_us[v]) m = (uint8_t)(m | (1u << v));
    return m;
}

void board_note(int what, uint32_t a, uint32_t b)
{
    if (!plog) return;
    switch (what) {
    case VC_NOTE_ABORT: fprintf(plog, "abort %lu %lu\n", (unsigned long)a, (unsigned long)b); break;
    case VC_NOTE_FAULT: fprintf(plog, "fault %lu %lu\n", (unsigned long)a, (unsigned long)b); break;
    case VC_NOTE_DONE: fprintf(plog, "done %lu %lu\n", (unsigned long)a, (unsigned long)b); break;
    case VC_NOTE_START: fprintf(plog, "start %lu %lu\n", (unsigned long)a, (unsigned long)b); break;
    default: break;
    }
    fflush(plog);
}

void board_stall(uint32_t ms) { stall_ms = ms; }
/* one thread: the tick never interrupts the core */
uint32_t board_lock(void) { return 0; }
void board_unlock(uint32_t saved) { (void)saved; }

/* ------------------------------------------------------------------ process */

static uint64_t mono_us(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (uint64_t)ts.tv_sec * 1000000u + (uint64_t)ts.tv_nsec / 1000u;
}

static void on_signal(int sig)
{
    if (sig == SIGUSR1) got_trigger = 1;
    else got_stop = 1;
}

static void flush_tx(void)
{
    while (txlen) {
        ssize_t k = write(master, txbuf, txlen);
        if (k <= 0) return;                      /* EAGAIN: the pty is full; later */
        memmove(txbuf, txbuf + k, txlen - (size_t)k);
        txlen -= (size_t)k;
    }
}

/* 1 if a SIGUSR1 is pending (blocked: it comes outside pselect), taken without its
 * handler. */
static int take_pending_trigger(void)
{
    sigset_t pend, usr1;
    struct timespec zero = {0, 0};
    if (sigpending(&pend) || !sigismember(&pend, SIGUSR1)) return 0;
    sigemptyset(&usr1);
    sigaddset(&usr1, SIGUSR1);
    return sigtimedwait(&usr1, 0, &zero) == SIGUSR1;
}

static int usage(void)
{
    fprintf(stderr, "usage: valvectl [--clock real|virtual] [--speed F] [--pty-file PATH] "
                    "[--pulse-log PATH] [--watchdog-ms MS]\n");
    return 2;
}

int main(int argc, char **argv)
{
    const char *pty_file = 0, *log_file = 0;
    uint32_t watchdog_ms = VC_WATCHDOG_MS;
    char *slave_name;
    int slave, i;
    struct termios tio;
    struct sigaction sa;
    sigset_t block, wait_mask;
    uint64_t t0, last_feed, ticks_done = 0, period_us;
    uint8_t buf[4096];

    for (i = 1; i < argc; i++) {
        if (!strcmp(argv[i], "--clock") && i + 1 < argc) {
            i++;
            if (!strcmp(argv[i], "virtual")) virtual_clock = 1;
            else if (strcmp(argv[i], "real")) return usage();
        } else if (!strcmp(argv[i], "--speed") && i + 1 < argc) {
            speed = atof(argv[++i]);
            if (!(speed > 0.0 && speed <= 1000.0)) return usage();
        } else if (!strcmp(argv[i], "--pty-file") && i + 1 < argc) {
            pty_file = argv[++i];
        } else if (!strcmp(argv[i], "--pulse-log") && i + 1 < argc) {
            log_file = argv[++i];
        } else if (!strcmp(argv[i], "--watchdog-ms") && i + 1 < argc) {
            watchdog_ms = (uint32_t)strtoul(argv[++i], 0, 10);
            if (watchdog_ms == 0) return usage();
        } else {
            return usage();
        }
    }
    if (log_file) {
        /* appended to: a reader may truncate the log between plays, and the next line
           goes to its new end (the virtual cell's log grew 1.5 GB over a 300 mm part) */
        int fd = open(log_file, O_WRONLY | O_CREAT | O_TRUNC | O_APPEND, 0666);
        if (fd < 0 || !(plog = fdopen(fd, "a"))) { perror(log_file); return 1; }
    }

    master = posix_openpt(O_RDWR | O_NOCTTY);
    if (master < 0 || grantpt(master) || unlockpt(master) || !(slave_name = ptsname(master))) {
        perror("pty");
        return 1;
    }
    /* keep the slave open ourselves, raw: no echo before a client sets its own mode, and no
     * hang-up when a client closes it */
    slave = open(slave_name, O_RDWR | O_NOCTTY);
    if (slave < 0 || tcgetattr(slave, &tio)) { perror(slave_name); return 1; }
    cfmakeraw(&tio);
    cfsetispeed(&tio, B115200);
    cfsetospeed(&tio, B115200);
    tcsetattr(slave, TCSANOW, &tio);
    fcntl(master, F_SETFL, fcntl(master, F_GETFL) | O_NONBLOCK);

    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal;
    sigaction(SIGUSR1, &sa, 0);
    sigaction(SIGTERM, &sa, 0);
    sigaction(SIGINT, &sa, 0);
    signal(SIGPIPE, SIG_IGN);
    /* the signals are taken only inside pselect (wait_mask): a trigger or stop that comes
     * between the loop's checks and the wait ends the wait instead of waiting 20 ms */
    sigemptyset(&block);
    sigaddset(&block, SIGUSR1);
    sigaddset(&block, SIGTERM);
    sigaddset(&block, SIGINT);
    sigprocmask(SIG_BLOCK, &block, &wait_mask);

    if (pty_file) {
        char tmp[4096];
        FILE *f;
        snprintf(tmp, sizeof tmp, "%s.tmp", pty_file);
        if (!(f = fopen(tmp, "w"))) { perror(tmp); return 1; }
        fprintf(f, "%s\n", slave_name);
        fclose(f);
        rename(tmp, pty_file);
    }
    printf("PTY %s\nPID %ld\n", slave_name, (long)getpid());
    fflush(stdout);

    vc_init(&core, VC_RESET_POWER);
    core.wait_for_data = (uint8_t)virtual_clock;
    period_us = (uint64_t)(VC_TICK_US / speed);
    if (period_us == 0) period_us = 1;
    t0 = last_feed = mono_us();

    while (!got_stop) {
        fd_set rd, wr;
        struct timespec wait;
        uint64_t now = mono_us();
        uint64_t wait_us = 20000;                /* at most 20 ms between passes */
        int idle = 0, n;
        if (!virtual_clock) {
            if (!vc_needs_tick(&core) && !got_trigger) {
                idle = 1;                        /* no tick has work: wait for a frame,
                                                    the trigger or 20 ms (not for a tick) */
            } else {
                uint64_t next_at = t0 + (ticks_done + 1) * period_us;
                wait_us = next_at <= now ? 0 : next_at - now;
                /* under the kernel's timer slack (~50 us) a wait wakes late: at --speed
                 * 10 and above (ticks of 200 us and less) the ticks are met by polling */
                if (wait_us < 200) wait_us = 0;
                if (wait_us > 20000) wait_us = 20000;
            }
        } else if (vc_needs_tick(&core) && vc_can_advance(&core)) {
            wait_us = 0;
        }
        if (got_trigger || got_stop) wait_us = 0;
        FD_ZERO(&rd);
        FD_ZERO(&wr);
        FD_SET(master, &rd);
        if (txlen) FD_SET(master, &wr);
        wait.tv_sec = (time_t)(wait_us / 1000000u);
        wait.tv_nsec = (long)(wait_us % 1000000u) * 1000L;
        n = pselect(master + 1, &rd, &wr, 0, &wait, &wait_mask);
        if (n < 0 && errno != EINTR) break;
        if (n < 0) { FD_ZERO(&rd); }
        now = mono_us();
        if (!virtual_clock) {
            if (idle) ticks_done = (now - t0) / period_us;  /* the idle ticks did nothing */
            ctrl_us = (uint64_t)((double)(now - t0) * speed);   /* for STATUS's outputs */
        }
        if (FD_ISSET(master, &rd)) {
            ssize_t k = read(master, buf, sizeof buf);
            if (k > 0) vc_rx(&core, buf, (unsigned)k, (uint32_t)(now / 1000u));
        }
        vc_poll(&core, (uint32_t)(now / 1000u));
        if (got_trigger) { got_trigger = 0; vc_trigger_edge(&core); }

        if (!virtual_clock) {
            uint64_t due = (now - t0) / period_us;
            while (ticks_done < due) {
                uint64_t due_at = t0 + (ticks_done + 1) * period_us;
                ctrl_us = (uint64_t)((double)(now - t0) * speed);
                vc_tick(&core, now > due_at + period_us);
                ticks_done++;
                if (!vc_needs_tick(&core)) { ticks_done = due; break; }
            }
            ctrl_us = (uint64_t)((double)(now - t0) * speed);
        } else {
            int k;
            for (k = 0; k < 512 && vc_needs_tick(&core) && vc_can_advance(&core); k++) {
                if (!vc_tick(&core, 0)) break;           /* waits for program bytes */
                ctrl_us += VC_TICK_US;
            }
            if (!vc_needs_tick(&core)) {        /* time passes to the last pulse's end */
                unsigned v;
                for (v = 0; v < VC_N_VALVES; v++)
                    if (off_us[v] > ctrl_us) ctrl_us = off_us[v];
            }
        }
        last_feed = now;                         /* the main loop feeds the watchdog */

        if (stall_ms) {                          /* STALL: the main loop hangs */
            uint32_t ms = stall_ms;
            stall_ms = 0;
            flush_tx();
            if (virtual_clock) {
                if (ms >= watchdog_ms) {
                    vc_init(&core, VC_RESET_WATCHDOG);
                    core.wait_for_data = 1;
                }
            } else {
                uint64_t until = now + (uint64_t)ms * 1000u;
                for (;;) {                       /* ticks go on (interrupt); frames do not */
                    uint64_t n2 = mono_us();
                    uint64_t due = (n2 - t0) / period_us;
                    if (n2 - last_feed >= (uint64_t)watchdog_ms * 1000u) {
                        vc_init(&core, VC_RESET_WATCHDOG);   /* the watchdog resets the MCU */
                        ticks_done = due;
                        break;
                    }
                    if (n2 >= until) break;
                    /* the board's tick samples the trigger pin while its main loop hangs:
                     * take the edge here (SIGUSR1 waits, blocked, for the main loop's
                     * pselect), not after frames sent meanwhile (an ARM would take it) */
                    if (ticks_done < due && take_pending_trigger()) vc_trigger_edge(&core);
                    while (ticks_done < due) {
                        ctrl_us = (uint64_t)((double)(n2 - t0) * speed);
                        vc_tick(&core, 0);
                        ticks_done++;
                    }
                    usleep(1000);
                }
            }
        }
        flush_tx();
        if (plog) fflush(plog);
    }
    board_valves_off();
    if (plog) { fprintf(plog, "exit\n"); fclose(plog); }
    flush_tx();
    close(slave);
    close(master);
    return 0;
}
