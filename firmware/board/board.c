/* The emulated estimator board: the real firmware (an ELF built by firmware/Makefile) on simavr's
 * ATmega328P, its analog pins driven from a table of millivolts, its UART on a pseudo-terminal or in a
 * file. Written for Debian's simavr 1.6 API (docs/live.md, "The emulated board").
 *
 *   board --elf build/needlecue.elf --table trial.csv [--pty LINK | --tx FILE] [options]
 *
 * --table CSV       header, then rows "t_s,mv0,mv1,...": pin k holds mv<k> from t_s on (sim seconds since
 *                   power-on); before the first row, the first row's values
 * --seconds S       stop after S seconds of board time (default: until SIGTERM)
 * --pty LINK        the UART on a new pseudo-terminal, LINK a symlink to it. The board powers on when a
 *                   reader opens it (as an Uno resets when the port opens) and runs at real time
 * --tx FILE         every byte the UART sends, in a file; the board runs as fast as the host allows
 * --rx-at S:TEXT    TEXT (\n for a newline) into the UART at S
 * --events FILE     "S <ns>" the instant of each sample (the first conversion of pin 0 after another
 *                   pin's), "R <ns>" a reset, "D <ns> <bytes>" bytes the host did not take in time
 * --freq HZ         the crystal (default 16000000; the firmware still assumes 16 MHz)
 * --reset-at S      reset the board at S (repeatable)
 * --boot-ms MS      the board starts MS after power-on and each reset (the bootloader's wait)
 * --stuck PIN:FROM:TO:MV   pin PIN reads MV from FROM to TO seconds (a broken wire, a stuck channel)
 * --crosstalk F     the first conversion after the multiplexer switched pins reads F of the previous
 *                   pin's voltage (the sample-and-hold capacitor behind a high-impedance source)
 * --dev-buf BYTES   bytes the USB link holds for a host that does not read (64..4095, default 4000); more is lost
 * --eeprom FILE     the EEPROM's 1024 bytes, read at the start if the file exists, written at the end
 * --wait-reader S   with --pty, give up if nobody opens it within S seconds (default 60)
 *
 * At the end it prints one line of JSON: board time, samples, resets, bytes sent and lost.
 */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <pty.h>
#include <signal.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/ioctl.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include "avr_adc.h"
#include "avr_eeprom.h"
#include "avr_uart.h"
#include "sim_avr.h"
#include "sim_elf.h"

#define MAX_PINS 8
#define MAX_EVENTS 64
#define EEPROM_SIZE 1024

typedef struct {
	double t;
	uint32_t mv[MAX_PINS];
} row_t;

typedef struct {
	double at;
	int kind; /* 'R' reset, 'X' text into the UART */
	char *text;
} event_t;

typedef struct {
	int pin;
	double from, to;
	uint32_t mv;
} stuck_t;

static struct {
	avr_t *avr;
	uint64_t base;       /* cycles of board time not in avr->cycle (boot waits; a reset that zeroes it) */
	uint64_t hold_until; /* the core waits (bootloader) until this board cycle */
	row_t *rows;
	size_t n_rows, cursor;
	int n_pins;
	event_t events[MAX_EVENTS];
	int n_events, next_event;
	stuck_t stuck[MAX_EVENTS];
	int n_stuck;
	double crosstalk;
	int last_src;
	uint32_t last_mv;
	FILE *events_out, *tx_out;
	int master, slave;
	size_t dev_buf;
	uint8_t tx[1 << 16];
	size_t tx_len;
	uint8_t rx[4096];
	size_t rx_len, rx_pos;
	int xon;
	avr_irq_t *uart;
	uint64_t samples, resets, tx_bytes, lost_bytes, behind_max_ns;
} B;

static volatile sig_atomic_t stop_requested;
static void on_signal(int sig) { (void)sig; stop_requested = 1; }

static void die(const char *what, const char *detail) {
	fprintf(stderr, "board: %s%s%s\n", what, detail ? ": " : "", detail ? detail : "");
	exit(2);
}

static uint64_t now_cycles(void) { return B.base + B.avr->cycle; }
static uint64_t cycles_ns(uint64_t c) { return (uint64_t)((unsigned __int128)c * 1000000000u / B.avr->frequency); }
static double board_s(void) { return (double)now_cycles() / B.avr->frequency; }

static uint64_t wall_ns(void) {
	struct timespec ts;
	clock_gettime(CLOCK_MONOTONIC, &ts);
	return (uint64_t)ts.tv_sec * 1000000000u + ts.tv_nsec;
}

/* ---- the analog pins ---------------------------------------------------------------------------- */
static void load_table(const char *path) {
	FILE *f = fopen(path, "r");
	if (!f) die("cannot read the table", path);
	char line[1024];
	size_t cap = 1024, lineno = 1;
	if (!fgets(line, sizeof line, f)) die("empty table", path);
	for (char *p = line; *p; p++) B.n_pins += *p == ',';
	if (B.n_pins < 1 || B.n_pins > MAX_PINS) die("the table needs t_s and 1 to 8 pins", path);
	B.rows = malloc(cap * sizeof *B.rows);
	while (fgets(line, sizeof line, f)) {
		lineno++;
		if (B.n_rows == cap) B.rows = realloc(B.rows, (cap *= 2) * sizeof *B.rows);
		row_t *r = &B.rows[B.n_rows];
		char *p = line, *end;
		r->t = strtod(p, &end);
		for (int k = 0; k < B.n_pins; k++) {
			if (*end != ',') {
				fprintf(stderr, "board: %s:%zu: expected %d pins\n", path, lineno, B.n_pins);
				exit(2);
			}
			r->mv[k] = (uint32_t)strtoul(end + 1, &end, 10);
		}
		if (B.n_rows && r->t < B.rows[B.n_rows - 1].t) {
			fprintf(stderr, "board: %s:%zu: t_s goes back\n", path, lineno);
			exit(2);
		}
		B.n_rows++;
	}
	fclose(f);
	if (!B.n_rows) die("a table without rows", path);
}

static uint32_t pin_mv(int pin, double t) {
	for (int i = 0; i < B.n_stuck; i++)
		if (B.stuck[i].pin == pin && t >= B.stuck[i].from && t < B.stuck[i].to) return B.stuck[i].mv;
	if (!B.n_rows || pin >= B.n_pins) return 0;
	while (B.cursor + 1 < B.n_rows && B.rows[B.cursor + 1].t <= t) B.cursor++;
	return B.rows[B.cursor].mv[pin];
}

/* simavr 1.6 raises OUT_TRIGGER when the firmware starts a conversion and computes the count from the
 * millivolts last raised on the pin when the firmware reads the result: answer with the pin's voltage */
static void on_conversion(avr_irq_t *irq, uint32_t value, void *param) {
	(void)irq, (void)param;
	union { avr_adc_mux_t mux; uint32_t v; } u = {.v = value};
	if (u.mux.kind != ADC_MUX_SINGLE) return;
	int src = u.mux.src;
	uint32_t mv = pin_mv(src, board_s());
	if (src == 0 && B.last_src != 0) {  /* a new sample starts with pin 0 */
		B.samples++;
		if (B.events_out) fprintf(B.events_out, "S %llu\n", (unsigned long long)cycles_ns(now_cycles()));
	}
	if (B.last_src >= 0 && src != B.last_src && B.crosstalk > 0)
		mv = (uint32_t)lround((1 - B.crosstalk) * mv + B.crosstalk * B.last_mv);
	B.last_src = src;
	B.last_mv = mv;
	avr_raise_irq(avr_io_getirq(B.avr, AVR_IOCTL_ADC_GETIRQ, src), mv);
}

/* ---- the UART ------------------------------------------------------------------------------------ */
static void on_tx(avr_irq_t *irq, uint32_t value, void *param) {
	(void)irq, (void)param;
	B.tx_bytes++;
	if (B.tx_out) fputc((int)value, B.tx_out);
	if (B.master >= 0) {
		if (B.tx_len < sizeof B.tx) B.tx[B.tx_len++] = (uint8_t)value;
		else B.lost_bytes++;
	}
}
/* simavr raises XOFF with 0 just before XON with 1: only a raised line changes the state */
static void on_xon(avr_irq_t *irq, uint32_t value, void *param) { (void)irq, (void)param; if (value) B.xon = 1; }
static void on_xoff(avr_irq_t *irq, uint32_t value, void *param) { (void)irq, (void)param; if (value) B.xon = 0; }

static void feed_rx(void) {
	while (B.xon && B.rx_pos < B.rx_len) avr_raise_irq(B.uart + UART_IRQ_INPUT, B.rx[B.rx_pos++]);
	if (B.rx_pos == B.rx_len) B.rx_pos = B.rx_len = 0;
}

static void queue_rx(const char *s, size_t n) {
	if (B.rx_len + n > sizeof B.rx) n = sizeof B.rx - B.rx_len;
	memcpy(B.rx + B.rx_len, s, n);
	B.rx_len += n;
}

/* ---- the pseudo-terminal: what the USB-serial bridge and the host's driver do --------------------- */
static int reader_present(void) {
	struct termios t;
	return tcgetattr(B.slave, &t) == 0 && !(t.c_lflag & ICANON);  /* pyserial makes the port raw */
}

static void service_pty(void) {
	if (B.tx_len) {
		int unread = 0;
		ioctl(B.slave, TIOCINQ, &unread);
		size_t room = unread >= (int)B.dev_buf ? 0 : B.dev_buf - unread;
		/* a slice that does not fit is lost whole: a bridge that is full takes nothing */
		size_t n = B.tx_len <= room ? B.tx_len : 0, written = 0;
		while (written < n) {
			ssize_t w = write(B.master, B.tx + written, n - written);
			if (w <= 0) break;
			written += w;
		}
		if (written < B.tx_len) {  /* the bridge's buffer is full: these bytes are gone */
			B.lost_bytes += B.tx_len - written;
			if (B.events_out)
				fprintf(B.events_out, "D %llu %zu\n", (unsigned long long)cycles_ns(now_cycles()), B.tx_len - written);
		}
		B.tx_len = 0;
	}
	char buf[256];
	ssize_t n = read(B.master, buf, sizeof buf);
	if (n > 0) queue_rx(buf, (size_t)n);
}

static void open_pty(const char *link) {
	char name[256];
	if (openpty(&B.master, &B.slave, name, NULL, NULL) != 0) die("openpty failed", strerror(errno));
	fcntl(B.master, F_SETFL, fcntl(B.master, F_GETFL) | O_NONBLOCK);
	unlink(link);
	if (symlink(name, link) != 0) die("cannot make the link", link);
	printf("board: %s (link %s)\n", name, link);
	fflush(stdout);
}

/* ---- resets, boot --------------------------------------------------------------------------------- */
static uint64_t boot_cycles;

static void start_boot(void) {
	B.hold_until = now_cycles() + boot_cycles;
	B.last_src = -1;
}

static void reset_board(void) {
	uint64_t before = B.avr->cycle;
	avr_reset(B.avr);
	if (B.avr->cycle < before) B.base += before - B.avr->cycle;  /* newer simavr zeroes the count */
	B.resets++;
	if (B.events_out) fprintf(B.events_out, "R %llu\n", (unsigned long long)cycles_ns(now_cycles()));
	start_boot();
}

static void decode_text(char *s) {  /* "\n" in an argument is a newline */
	char *o = s;
	for (char *p = s; *p; p++) {
		if (p[0] == '\\' && p[1] == 'n') *o++ = '\n', p++;
		else *o++ = *p;
	}
	*o = 0;
}

static int by_time(const void *a, const void *b) {
	double d = ((const event_t *)a)->at - ((const event_t *)b)->at;
	return (d > 0) - (d < 0);
}

int main(int argc, char **argv) {
	const char *elf = NULL, *table = NULL, *link = NULL, *tx = NULL, *events = NULL, *eeprom = NULL;
	double seconds = INFINITY, wait_reader = 60, boot_ms = 0;
	uint32_t freq = 16000000;
	B.dev_buf = 4000;
	B.master = B.slave = -1;
	for (int i = 1; i < argc; i++) {
		const char *a = argv[i], *v = i + 1 < argc ? argv[i + 1] : NULL;
		if (!v) die("a value is missing after", a);
		i++;
		if (!strcmp(a, "--elf")) elf = v;
		else if (!strcmp(a, "--table")) table = v;
		else if (!strcmp(a, "--pty")) link = v;
		else if (!strcmp(a, "--tx")) tx = v;
		else if (!strcmp(a, "--events")) events = v;
		else if (!strcmp(a, "--eeprom")) eeprom = v;
		else if (!strcmp(a, "--seconds")) seconds = atof(v);
		else if (!strcmp(a, "--wait-reader")) wait_reader = atof(v);
		else if (!strcmp(a, "--freq")) freq = (uint32_t)atol(v);
		else if (!strcmp(a, "--boot-ms")) boot_ms = atof(v);
		else if (!strcmp(a, "--crosstalk")) B.crosstalk = atof(v);
		else if (!strcmp(a, "--dev-buf")) B.dev_buf = (size_t)atol(v);
		else if ((!strcmp(a, "--reset-at") || !strcmp(a, "--rx-at")) && B.n_events < MAX_EVENTS) {
			event_t *e = &B.events[B.n_events++];
			e->at = atof(v);
			e->kind = a[2] == 'r' && a[3] == 'e' ? 'R' : 'X';
			if (e->kind == 'X') {
				const char *colon = strchr(v, ':');
				if (!colon) die("--rx-at wants S:TEXT", v);
				e->text = strdup(colon + 1);
				decode_text(e->text);
			}
		} else if (!strcmp(a, "--stuck") && B.n_stuck < MAX_EVENTS) {
			stuck_t *s = &B.stuck[B.n_stuck++];
			if (sscanf(v, "%d:%lf:%lf:%u", &s->pin, &s->from, &s->to, &s->mv) != 4) die("--stuck wants PIN:FROM:TO:MV", v);
		} else die("unknown option", a);
	}
	if (!elf) die("--elf is required", NULL);
	/* TIOCINQ cannot say more than the terminal's 4095-byte buffer holds: a larger bridge buffer would
	 * never fill, and the kernel's overflow would pass fragments of lines on instead */
	if (B.dev_buf < 64 || B.dev_buf > 4095) die("--dev-buf is 64 to 4095 bytes", NULL);
	qsort(B.events, B.n_events, sizeof *B.events, by_time);
	if (table) load_table(table);
	boot_cycles = (uint64_t)(boot_ms / 1000 * freq);

	/* simavr 1.6 prints what it loads on stdout, whatever the log level: our stdout is the summary */
	fflush(stdout);
	int saved_stdout = dup(1), devnull = open("/dev/null", O_WRONLY);
	dup2(devnull, 1);
	elf_firmware_t fw;
	memset(&fw, 0, sizeof fw);
	int read_failed = elf_read_firmware(elf, &fw);
	B.avr = avr_make_mcu_by_name("atmega328p");
	if (!read_failed && B.avr) {
		avr_init(B.avr);
		B.avr->log = LOG_ERROR;
		avr_load_firmware(B.avr, &fw);
	}
	fflush(stdout);
	dup2(saved_stdout, 1);
	close(devnull);
	close(saved_stdout);
	if (read_failed) die("cannot read the firmware", elf);
	if (!B.avr) die("simavr has no atmega328p", NULL);
	B.avr->frequency = freq;
	B.avr->vcc = B.avr->avcc = B.avr->aref = 5000;  /* mV: the Uno's 5 V, AVCC the ADC's reference */

	if (eeprom) {
		FILE *f = fopen(eeprom, "rb");
		if (f) {
			uint8_t ee[EEPROM_SIZE];
			size_t n = fread(ee, 1, sizeof ee, f);
			fclose(f);
			avr_eeprom_desc_t d = {.ee = ee, .offset = 0, .size = (uint32_t)n};
			avr_ioctl(B.avr, AVR_IOCTL_EEPROM_SET, &d);  /* 1.6 returns -1 even when it worked */
		}
	}
	avr_irq_register_notify(avr_io_getirq(B.avr, AVR_IOCTL_ADC_GETIRQ, ADC_IRQ_OUT_TRIGGER), on_conversion, NULL);
	B.uart = avr_io_getirq(B.avr, AVR_IOCTL_UART_GETIRQ('0'), 0);
	uint32_t flags = 0;
	avr_ioctl(B.avr, AVR_IOCTL_UART_GET_FLAGS('0'), &flags);
	flags &= ~(AVR_UART_FLAG_STDIO | AVR_UART_FLAG_POLL_SLEEP);  /* no echo to the console, no usleep */
	avr_ioctl(B.avr, AVR_IOCTL_UART_SET_FLAGS('0'), &flags);
	avr_irq_register_notify(B.uart + UART_IRQ_OUTPUT, on_tx, NULL);
	avr_irq_register_notify(B.uart + UART_IRQ_OUT_XON, on_xon, NULL);
	avr_irq_register_notify(B.uart + UART_IRQ_OUT_XOFF, on_xoff, NULL);
	B.xon = 1;

	if (events && !(B.events_out = fopen(events, "w"))) die("cannot write", events);
	if (tx && !(B.tx_out = fopen(tx, "wb"))) die("cannot write", tx);
	signal(SIGTERM, on_signal);
	signal(SIGINT, on_signal);
	signal(SIGPIPE, SIG_IGN);

	int paced = link != NULL;
	if (paced) {
		open_pty(link);
		uint64_t give_up = wall_ns() + (uint64_t)(wait_reader * 1e9);
		while (!reader_present() && !stop_requested) {
			if (wall_ns() > give_up) {
				unlink(link);
				die("nobody opened the port", link);
			}
			usleep(10000);
		}
	}
	start_boot();
	uint64_t t0 = wall_ns();
	uint64_t slice = B.avr->frequency / 1000;  /* 1 ms of board time between services */
	int state = cpu_Running;
	while (!stop_requested && board_s() < seconds) {
		uint64_t end = now_cycles() + slice;
		if (now_cycles() < B.hold_until) {
			B.base += slice;  /* the bootloader's wait: time passes, the sketch has not started */
		} else {
			while (now_cycles() < end) {
				state = avr_run(B.avr);
				if (state == cpu_Done || state == cpu_Crashed) goto out;
			}
		}
		while (B.next_event < B.n_events && B.events[B.next_event].at <= board_s()) {
			event_t *e = &B.events[B.next_event++];
			if (e->kind == 'R') reset_board();
			else queue_rx(e->text, strlen(e->text));
		}
		if (paced) service_pty();
		feed_rx();
		if (paced) {
			uint64_t sim = cycles_ns(now_cycles()), wall = wall_ns() - t0;
			if (sim > wall) {
				struct timespec ts = {.tv_sec = (sim - wall) / 1000000000u, .tv_nsec = (sim - wall) % 1000000000u};
				nanosleep(&ts, NULL);
			} else if (wall - sim > B.behind_max_ns) {
				B.behind_max_ns = wall - sim;
			}
		}
	}
out:
	if (paced) service_pty();
	if (eeprom) {
		avr_eeprom_desc_t d = {.ee = NULL, .offset = 0, .size = EEPROM_SIZE};
		avr_ioctl(B.avr, AVR_IOCTL_EEPROM_GET, &d);  /* with ee NULL: a pointer to simavr's own bytes */
		FILE *f = fopen(eeprom, "wb");
		if (!f || !d.ee || fwrite(d.ee, 1, EEPROM_SIZE, f) != EEPROM_SIZE) die("cannot write", eeprom);
		fclose(f);
	}
	if (B.events_out) fclose(B.events_out);
	if (B.tx_out) fclose(B.tx_out);
	if (link) unlink(link);
	printf("{\"board_s\": %.6f, \"cycles\": %llu, \"samples\": %llu, \"resets\": %llu, \"tx_bytes\": %llu, "
	       "\"lost_bytes\": %llu, \"behind_max_s\": %.6f, \"state\": %d}\n",
	       board_s(), (unsigned long long)now_cycles(), (unsigned long long)B.samples, (unsigned long long)B.resets,
	       (unsigned long long)B.tx_bytes, (unsigned long long)B.lost_bytes, B.behind_max_ns / 1e9, state);
	return state == cpu_Crashed ? 3 : 0;
}
