// needlecue estimator firmware for an Arduino Uno (ATmega328P at 16 MHz): the force-sensing resistors'
// voltages over USB serial in the wire format needlecue-wire/1 (docs/live.md).
//
// The sample clock is Timer1 in CTC mode: its interrupt starts a chain of ADC conversions, which the
// ADC interrupt carries through every channel (settling conversions discarded, the rest averaged). The
// results go through a small ring to loop(), which alone formats and prints, and reads commands.
// Nothing waits on millis(): a late print never moves the next sample.
#include <avr/eeprom.h>
#include <util/atomic.h>
#include <util/crc16.h>

#include "config.h"

#define MUX_OF(pin, name) pin,
#define NAME_OF(pin, name) "," name
static const uint8_t MUX[] = {NC_CHANNELS(MUX_OF)};
static const uint8_t N = sizeof MUX;
static const char NAMES[] PROGMEM = NC_CHANNELS(NAME_OF);  // ",fsr1,fsr2,fsr3": skip the first comma

// Timer1 at F_CPU/64 (4 us a tick at 16 MHz): the compare value nearest the rate.
#define NC_PRESCALE 64UL
#define NC_TOP ((F_CPU + NC_PRESCALE * NC_RATE_HZ / 2) / (NC_PRESCALE * NC_RATE_HZ) - 1)
static_assert(NC_TOP > 0 && NC_TOP < 65536UL, "NC_RATE_HZ out of Timer1's range at this prescaler");
// each sample must carry a later millis() than the last: the host reads an equal one as a restart
static_assert(NC_RATE_HZ <= 500, "NC_RATE_HZ above 500: two samples could carry the same millis()");
// the rate Timer1 really gives, in millihertz, must be within 0.1 % of the declared one
#define NC_RATE_MHZ (F_CPU * 1000ULL / NC_PRESCALE / (NC_TOP + 1))
#define NC_DECLARED_MHZ (NC_RATE_HZ * 1000ULL)
static_assert((NC_RATE_MHZ > NC_DECLARED_MHZ ? NC_RATE_MHZ - NC_DECLARED_MHZ : NC_DECLARED_MHZ - NC_RATE_MHZ)
                  <= NC_DECLARED_MHZ / 1000, "Timer1 cannot give NC_RATE_HZ within 0.1 %");
static_assert(NC_OVERSAMPLE >= 1 && NC_OVERSAMPLE <= 64, "NC_OVERSAMPLE: 1..64 (a 16-bit sum of 10-bit counts)");
static_assert(NC_DISCARD + NC_OVERSAMPLE <= 255, "conversions per channel are counted in 8 bits");
// one sample's conversions (13 ADC clocks at 125 kHz each) must end well within the sample period
static_assert(N * (NC_DISCARD + NC_OVERSAMPLE) * 104UL * NC_RATE_HZ < 500000UL, "too many conversions per sample");

// ---- sampling: interrupts only ----------------------------------------------------------------------
struct Reading {
  uint32_t ms;
  uint16_t counts[N];
};
static const uint8_t SLOTS = 8;  // loop() may fall 7 samples behind (saving an id in EEPROM: ~90 ms)
static Reading ring[SLOTS];
static volatile uint8_t head, tail;  // ISR writes ring[head], loop() reads ring[tail]
static volatile uint8_t busy;        // a conversion chain is under way
static volatile uint16_t missed;     // samples not taken (chain still busy) or not kept (ring full)
static uint8_t channel, conversions;
static uint16_t sum;

static inline void start_conversion(uint8_t c) {
  ADMUX = _BV(REFS0) | MUX[c];  // AVCC reference, right-adjusted
  ADCSRA |= _BV(ADSC);
}

ISR(TIMER1_COMPA_vect) {  // the sample clock
  if (busy) {
    missed++;
    return;
  }
  busy = 1;
  ring[head].ms = millis();
  channel = 0;
  conversions = 0;
  sum = 0;
  start_conversion(0);
}

ISR(ADC_vect) {
  uint16_t value = ADC;
  if (++conversions > NC_DISCARD) sum += value;  // the first NC_DISCARD after a switch are thrown away
  if (conversions < NC_DISCARD + NC_OVERSAMPLE) {
    ADCSRA |= _BV(ADSC);  // same channel again
    return;
  }
  ring[head].counts[channel] = (sum + NC_OVERSAMPLE / 2) / NC_OVERSAMPLE;
  sum = 0;
  conversions = 0;
  if (++channel < N) {
    start_conversion(channel);
    return;
  }
  uint8_t next = (head + 1) % SLOTS;
  if (next == tail)
    missed++;  // loop() is SLOTS samples behind: this one is dropped
  else
    head = next;
  busy = 0;
}

// ---- the unit id in EEPROM ----------------------------------------------------------------------------
// At address 0: 'N', 'C', length, the id (up to 23 characters), a CRC-8 of the id. A blank or damaged
// record means no id: the banner then leaves `unit=` out.
static const uint8_t ID_MAX = 23;
static char unit_id[ID_MAX + 1];

static uint8_t crc8(const char *s, uint8_t n) {  // over the length and the id
  uint8_t crc = _crc8_ccitt_update(0, n);
  while (n--) crc = _crc8_ccitt_update(crc, *s++);
  return crc;
}

static void load_id() {
  uint8_t rec[3 + ID_MAX + 1];
  eeprom_read_block(rec, (const void *)0, sizeof rec);
  uint8_t n = rec[2];
  unit_id[0] = 0;
  if (rec[0] != 'N' || rec[1] != 'C' || n == 0 || n > ID_MAX) return;
  if (crc8((const char *)rec + 3, n) != rec[3 + n]) return;
  memcpy(unit_id, rec + 3, n);
  unit_id[n] = 0;
}

static void save_id(const char *id, uint8_t n) {
  uint8_t rec[3 + ID_MAX + 1];
  rec[0] = 'N';
  rec[1] = 'C';
  rec[2] = n;
  memcpy(rec + 3, id, n);
  rec[3 + n] = crc8(id, n);
  eeprom_update_block(rec, (void *)0, 4 + n);  // blocks ~3.3 ms a byte: the ring holds the samples
  if (n == 0) eeprom_update_byte((uint8_t *)0, 0xFF);
  load_id();
}

static bool valid_id_char(char c) {
  return (c >= 'A' && c <= 'Z') || (c >= 'a' && c <= 'z') || (c >= '0' && c <= '9') || c == '.' || c == '_' ||
         c == '-';
}

// ---- output -------------------------------------------------------------------------------------------
static void print_banner() {
  Serial.print(F("#needlecue-wire/1"));
  if (unit_id[0]) {
    Serial.print(F(" unit="));
    Serial.print(unit_id);
  }
  Serial.print(F(" channels="));
  Serial.print((const __FlashStringHelper *)(NAMES + 1));
  Serial.print(F(" adc_bits=10 vref_v=" NC_VREF " rate_hz="));
  Serial.print(NC_RATE_HZ);
  Serial.print(F(" oversample="));
  Serial.print(NC_OVERSAMPLE);
  Serial.print(F(" fw=" NC_FW "\n"));
}

static void send(const Reading &r) {
  char line[11 + 5 * N + 1];  // "4294967295" then ",1023" per channel, "\n"
  char *p = line;
  ultoa(r.ms, p, 10);
  p += strlen(p);
  for (uint8_t c = 0; c < N; c++) {
    *p++ = ',';
    utoa(r.counts[c], p, 10);
    p += strlen(p);
  }
  *p++ = '\n';
  Serial.write((const uint8_t *)line, p - line);  // one write: a line is never split by other output
}

// ---- commands (docs/live.md): "ID <unit>" sets the unit id, "ID" clears it, "?" prints the banner ------
static char command[32];
static uint8_t command_len;
static bool command_too_long;

static void run_command() {
  if (command_too_long) {
    Serial.print(F("#error command longer than 31 characters\n"));
  } else if (strcmp(command, "?") == 0) {
    print_banner();
  } else if (strncmp(command, "ID", 2) == 0 && (command[2] == 0 || command[2] == ' ')) {
    const char *id = command[2] ? command + 3 : command + 2;
    uint8_t n = strlen(id);
    bool ok = n <= ID_MAX;
    for (uint8_t i = 0; ok && i < n; i++) ok = valid_id_char(id[i]);
    if (!ok) {
      Serial.print(F("#error id: 0 to 23 of A-Z a-z 0-9 . _ -\n"));
      return;
    }
    save_id(id, n);
    Serial.print(F("#id unit="));
    Serial.print(unit_id);
    Serial.print(F(" saved\n"));
  } else if (command_len) {
    Serial.print(F("#error unknown command (ID <unit>, ID, ?)\n"));
  }
}

static void read_commands() {  // one command per pass: each EEPROM write leaves the ring time to drain
  while (Serial.available()) {
    char c = Serial.read();
    if (c == '\r') continue;
    if (c == '\n') {
      command[command_len] = 0;
      run_command();
      command_len = 0;
      command_too_long = false;
      return;
    } else if (command_len < sizeof command - 1) {
      command[command_len++] = c;
    } else {
      command_too_long = true;
    }
  }
}

// ---- Arduino entry points -----------------------------------------------------------------------------
void setup() {
  Serial.begin(NC_BAUD);
  load_id();
  // init() left the ADC on at F_CPU/128 (125 kHz) and Timer1 in 8-bit PWM: take both over.
  ADMUX = _BV(REFS0) | MUX[0];  // AVCC now: the AREF pin's capacitor settles before the first sample
  ADCSRA |= _BV(ADIE);
  cli();
  TCCR1A = 0;
  TCCR1B = _BV(WGM12) | _BV(CS11) | _BV(CS10);  // CTC on OCR1A, F_CPU/64
  OCR1A = NC_TOP;
  TCNT1 = 0;
  TIFR1 = _BV(OCF1A);
  TIMSK1 = _BV(OCIE1A);
  sei();
  print_banner();
}

void loop() {
  static uint16_t reported;
  while (tail != head) {
    Reading r;
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE) { r = ring[tail]; }
    tail = (tail + 1) % SLOTS;
    send(r);
  }
  uint16_t m;
  ATOMIC_BLOCK(ATOMIC_RESTORESTATE) { m = missed; }
  if (m != reported) {  // a comment: the host sees the gap in millis and counts it anyway
    reported = m;
    Serial.print(F("#missed "));
    Serial.print(m);
    Serial.print('\n');
  }
  read_commands();
}
